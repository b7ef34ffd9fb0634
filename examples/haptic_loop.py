"""A haptic loop at 1 kHz: a tool follows a recorded trajectory into the liver; the loop prints the force
the device would render and, at the end, how well it kept its 1 ms period.

    .venv/bin/python examples/haptic_loop.py [--trajectory examples/palpation.csv] [--model linear-tm]
                                             [--seconds 3] [--rate 1000]

Each frame: ``set_tool`` moves the tool to the trajectory's point for the frame's time, ``step`` advances
the model by the frame's period in explicit substeps (half the critical step) and returns the force
each tool exerted on the body in its last substep (inertia and damping included); the device renders
its opposite. The loop then waits, sleeping and finally spinning, for the next tick of a fixed
schedule: a late frame does not shift the ones after it. Jitter is the frame's start minus its tick.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from meshes import stored_mesh
from realtime import Loading, Material, State, SymplecticEuler, build_model
from realtime.models import linear_tm

HERE = Path(__file__).parent


def read_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Times (T,) s and displacements (T, 3) m from a CSV with a header row t,dx,dy,dz ('#' comments)."""
    data = np.loadtxt(path, delimiter=",", comments="#", skiprows=0, dtype=str)
    if data.ndim != 2 or list(data[0]) != ["t", "dx", "dy", "dz"]:
        sys.exit(f"{path}: expected a header row t,dx,dy,dz and four columns")
    values = data[1:].astype(float)
    return values[:, 0], values[:, 1:]


def liver_with_a_tool(model_name: str, material: Material):
    """The stored liver held at the centre of its back, a translating tool on the surface vertices within
    8 mm of its highest point. No gravity: the liver rests in its stress-free shape, its weight borne by
    the organs around it (which the model leaves out), so that the device feels the palpation alone.
    The mesh is numbered along the body ("-renumbered", realtime.renumber), as a simulator numbers its
    own mesh once before it builds the model: the kernels then reuse more of what they load."""
    mesh = stored_mesh("liver-renumbered")
    p = mesh.points
    free = np.ones((mesh.n_vertices, 3))
    c = p.mean(axis=0)
    free[(p[:, 1] < p[:, 1].min() + 0.015) & (np.abs(p[:, 0] - c[0]) < 0.03)] = 0.0
    surface = mesh.surface_vertices
    top = surface[np.argmax(p[surface, 2])]
    contact = surface[np.linalg.norm(p[surface] - p[top], axis=1) < 0.008].astype(np.int64)
    free[contact] = 0.0
    loading = Loading.translating_tool(free, np.zeros((mesh.n_vertices, 3)), contact)
    return build_model(model_name, p, mesh.tets, material, loading), len(contact)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trajectory", type=Path, default=HERE / "palpation.csv")
    ap.add_argument("--model", default=linear_tm.NAME)
    ap.add_argument("--seconds", type=float, default=None, help="stop early (default: the whole trajectory)")
    ap.add_argument("--rate", type=float, default=1000.0, help="frames per second")
    args = ap.parse_args(argv)

    times, path = read_trajectory(args.trajectory)
    material = Material(2.8e4, 0.4, 1000.0, law="stvk")
    model, n_contact = liver_with_a_tool(args.model, material)
    period = 1.0 / args.rate
    integ = SymplecticEuler(alpha=20.0)  # mass damping: the liver's slowest modes settle in about 0.1 s
    substeps = max(1, math.ceil(period / (0.5 * integ.critical_dt(model))))
    dt = period / substeps
    state = State.at_rest(model.n_vertices)
    duration = times[-1] if args.seconds is None else min(args.seconds, times[-1])
    frames = int(duration * args.rate)
    print(
        f"{args.model} on the liver ({model.n_vertices} vertices, {len(model.tets)} tetrahedra), tool on "
        f"{n_contact} vertices; {frames} frames of {period * 1e3:.3g} ms, {substeps} steps of {dt * 1e6:.1f} us each"
    )
    integ.step(model, state, dt, 1)  # compiles the kernels before the clock starts
    state = State.at_rest(model.n_vertices)
    late = np.zeros(frames)
    busy = np.zeros(frames)
    start = time.perf_counter()
    for k in range(frames):
        tick = start + k * period
        now = time.perf_counter()
        late[k] = now - tick
        t = (k + 1) * period
        target = np.array([np.interp(t, times, path[:, c]) for c in range(3)])
        integ.set_tool(model, 0, translation=target)
        force = -integ.step(model, state, dt, substeps)[0]  # the body's push on the device, N
        busy[k] = time.perf_counter() - now
        if (k + 1) % int(args.rate / 4) == 0:
            print(
                f"t = {t:5.2f} s  tool {target[0] * 1e3:6.2f} {target[1] * 1e3:6.2f} {target[2] * 1e3:6.2f} mm"
                f"  device force {force[0]:7.3f} {force[1]:7.3f} {force[2]:7.3f} N  frame {busy[k] * 1e6:6.0f} us"
            )
        wait = tick + period - time.perf_counter()
        if wait > 3e-4:
            time.sleep(wait - 2e-4)  # the OS wakes us up to 0.1-0.2 ms late: spin the rest
        while time.perf_counter() < tick + period:
            pass
    missed = int(np.sum(late > period))
    print(
        f"{frames} frames: compute {np.median(busy) * 1e6:.0f} us median, {np.percentile(busy, 99) * 1e6:.0f} us "
        f"99th percentile; jitter {np.median(late) * 1e6:.0f} us median, {np.percentile(late, 99) * 1e6:.0f} us "
        f"99th percentile, {late.max() * 1e6:.0f} us worst; {missed} frames started a whole period late"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
