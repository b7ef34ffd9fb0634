"""The HTML report: its page (``page``), plots (``plots``) and the ParaView series (``vtk``)."""
