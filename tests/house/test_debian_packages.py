"""Nothing missing on a fresh machine: every module the test session loaded from outside the venv belongs
to a Debian package that the Makefile installs (directly or as a dependency).

``test_every_loaded_module_is_installed_by_the_makefile`` runs last (conftest moves it there), so it
sees ``sys.modules`` as the whole session left it, lazy imports (meshio's h5py) included.
"""

from __future__ import annotations

import os
import shutil
import sys

import pytest

from .debian_packages import MAKEFILE, OPTIONAL, makefile_packages, missing_packages

pytestmark = pytest.mark.skipif(
    shutil.which("dpkg") is None or sys.prefix == sys.base_prefix or not sys.base_prefix.startswith("/usr"),
    reason="needs Debian's dpkg and the project's venv over Debian's /usr/bin/python3",
)


@pytest.mark.run_last
def test_every_loaded_module_is_installed_by_the_makefile():
    missing = missing_packages()
    assert not missing, "loaded from Debian packages that the Makefile does not install: " + "; ".join(
        f"{pkg} ({', '.join(mods[:4])})" for pkg, mods in missing.items()
    )


def test_the_check_names_a_package_dropped_from_the_makefile(tmp_path):
    """The defect that reached a fresh machine once: meshio's XDMF writer needs python3-h5py. Without
    it in APT_PACKAGES the check must name it."""
    import h5py  # noqa: F401  (what meshio's XDMF writer imports lazily)

    packages = makefile_packages()
    assert "python3-h5py" in packages
    text = MAKEFILE.read_text().replace(" python3-h5py", "")
    assert "python3-h5py" not in makefile_packages_of(text, tmp_path)
    missing = missing_packages(tmp_path / "Makefile")
    assert any(pkg.startswith("python3-h5py") for pkg in missing), missing
    assert any("h5py" in mod for pkg, mods in missing.items() for mod in mods)


@pytest.mark.parametrize("package", sorted(OPTIONAL))
def test_optional_packages_are_really_optional(package):
    """What the check lets pass as optional must not be needed: its importer imports with it blocked."""
    import subprocess

    module, importer, _ = OPTIONAL[package]
    code = f"import sys; sys.modules[{module!r}] = None; import {importer}"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]


def makefile_packages_of(text: str, tmp_path) -> list[str]:
    (tmp_path / "Makefile").write_text(text)
    return makefile_packages(tmp_path / "Makefile")


def test_the_check_sees_the_shared_libraries_no_module_names():
    """numba's threads run in Debian's GNU OpenMP (libgomp), which a threaded model loads and no Python
    module names: the check must map it to its package, and the Makefile must install that package."""
    from meshes import stored_mesh
    from realtime import Material, build_model

    from .debian_packages import dependency_closure, loaded_libraries, owners

    mesh = stored_mesh("beam")
    build_model("stvk-tm", mesh.points, mesh.tets, Material(1e4, 0.3, 1000.0), threads=2).internal_force(
        mesh.points * 0
    )
    gomp = [f for f in loaded_libraries() if "libgomp.so" in f]
    assert gomp, "no libgomp mapped: the threaded kernels did not start GNU OpenMP"
    assert owners(gomp)[gomp[0]] == "libgomp1"
    assert "libgomp1" in makefile_packages()
    assert "libgomp1" in dependency_closure(makefile_packages())


def test_the_references_factorisations_run_in_an_optimised_blas_the_makefile_installs():
    """MUMPS's dense kernels run in whatever libblas.so.3 Debian's alternatives name. A fresh Debian 12
    has only the reference BLAS (libblas3), in which the stiff beam's refined Newmark matrix took 15 s to
    factorise, against 4 in OpenBLAS: the Makefile installs OpenBLAS, whose alternative outranks it.
    The BLAS this process mapped (numpy and PETSc load the same one) must not be libblas3's."""
    import numpy  # noqa: F401  (loads libblas.so.3)
    from petsc4py import PETSc  # noqa: F401

    from .debian_packages import loaded_libraries, owners

    blas = [f for f in loaded_libraries() if os.path.basename(f).startswith(("libblas.so", "libopenblas"))]
    assert blas, "no BLAS mapped"
    found = owners(blas)
    assert all(owner != "libblas3" for owner in found.values()), f"the reference BLAS is loaded: {found}"
    assert "libopenblas0-pthread" in makefile_packages()


@pytest.mark.slow
def test_under_xdist_the_controller_checks_what_every_worker_loaded(tmp_path):
    """``make test`` runs on xdist's workers, where the run_last check leaves the workers and the
    controller checks the union of what they loaded (conftest). Against a Makefile without python3-h5py,
    a worker that imported h5py must fail the run, with one line naming the package."""
    import os
    import subprocess

    text = MAKEFILE.read_text().replace(" python3-h5py", "")
    makefile = tmp_path / "Makefile"
    makefile.write_text(text)
    args = [sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider"]
    args += ["--basetemp", str(tmp_path / "t")]
    args += [f"{__file__}::test_every_loaded_module_is_installed_by_the_makefile"]
    args += [f"{__file__}::test_the_check_names_a_package_dropped_from_the_makefile"]
    env = dict(os.environ, TISSUEBENCH_CHECKED_MAKEFILE=str(makefile))
    env.pop("PYTEST_XDIST_WORKER", None)
    run = subprocess.run(args, capture_output=True, text=True, env=env, cwd=MAKEFILE.parent)
    lines = [line for line in run.stdout.splitlines() if "Debian package check" in line]
    assert run.returncode == 1, run.stdout[-3000:] + run.stderr[-2000:]
    assert len(lines) == 1 and "python3-h5py" in lines[0] and "h5py" in lines[0], run.stdout[-3000:]
    assert "1 passed" in run.stdout, run.stdout[-3000:]  # the h5py test; the run_last one left the workers


GENESIS_PYTHON = MAKEFILE.parent / ".venv-genesis" / "bin" / "python"


@pytest.mark.skipif(not GENESIS_PYTHON.exists(), reason="make genesis builds Genesis's venv")
def test_genesis_maps_only_libraries_make_genesis_installs(tmp_path):
    """``import genesis`` maps libGL and X11's client libraries (its viewer's pyrender and PyOpenGL, headless
    too), which a fresh Debian 12 lacks. Today python3-gmsh and chromium pull them in by chance (without
    python3-gmsh, libopengl0 is missing); make genesis installs GENESIS_APT_PACKAGES beside APT_PACKAGES.
    Every system library the import maps comes from those; with Genesis's own packages and python3-gmsh
    dropped, the check names libopengl0."""
    import re
    import subprocess

    from .debian_packages import loaded_libraries

    code = "import genesis; print(open('/proc/self/maps').read())"
    run = subprocess.run([str(GENESIS_PYTHON), "-c", code], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    (tmp_path / "maps").write_text(run.stdout)
    files = loaded_libraries(str(tmp_path / "maps"))
    assert any("libGL.so" in f for f in files), "import genesis mapped no libGL: the check sees nothing"
    assert not missing_packages(files=files, also=("GENESIS_APT_PACKAGES",))
    text = re.sub(r"(?m)^GENESIS_APT_PACKAGES\s*:=.*$", "GENESIS_APT_PACKAGES :=", MAKEFILE.read_text())
    assert "python3-gmsh" not in makefile_packages_of(text.replace(" python3-gmsh", ""), tmp_path)
    missing = missing_packages(tmp_path / "Makefile", files, also=("GENESIS_APT_PACKAGES",))
    assert "libopengl0" in missing, missing
