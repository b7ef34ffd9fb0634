"""Studies: what a user asks of many runs. One module each: ``sweep`` (error against speed over the
step), ``converge`` (orders in space and time), ``stability`` (the extremes), ``advise`` (the cheapest
model a scene needs at a rate), ``gates`` (CI accuracy gates), and ``seeds`` (the source documents'
experiments)."""
