"""Result files (docs/data-flow.md): one .npz per solver run, written atomically."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meshes.io import atomic_savez


@dataclass
class Result:
    """A solver run on a scene mesh of N vertices and M tetrahedra, at T output times.

    Attributes:
        points: (N, 3) float64 rest positions, m.
        tets: (M, 4) int64.
        times: (T,) float64 output times, s (a static result has T = 1).
        displacement: (T, N, 3) float64, m.
        reaction: (T, 3) float64 total force of the displacement loads on the body, N.
        meta: JSON-ready dict (scene name and hash, solver, model, dt, integrator, versions, timings).
    """

    points: np.ndarray
    tets: np.ndarray
    times: np.ndarray
    displacement: np.ndarray
    reaction: np.ndarray
    meta: dict

    def save(self, path: str | os.PathLike) -> Path:
        """Write to ``path`` through a temporary file in the same directory and a rename."""
        return atomic_savez(
            path,
            compressed=True,
            points=self.points,
            tets=self.tets,
            times=self.times,
            displacement=self.displacement,
            reaction=self.reaction,
            meta=np.array(json.dumps(self.meta, default=_jsonable)),
        )

    @staticmethod
    def load(path: str | os.PathLike) -> Result:
        with np.load(path, allow_pickle=False) as z:
            return Result(
                z["points"], z["tets"], z["times"], z["displacement"], z["reaction"], json.loads(str(z["meta"]))
            )


def _jsonable(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")
