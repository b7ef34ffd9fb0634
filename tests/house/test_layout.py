"""The house's layout holds (docs/architecture.md): no import circle, no file over 600 lines and no
function over 80, the numba kernels and the files that hold them included (a kernel file holds
kernels, not an exemption). Read from the sources, so
that a change that breaks one fails here, naming where."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("meshes", "realtime", "reference", "verification")
MAX_FILE_LINES, MAX_FUNCTION_LINES = 600, 80


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict) -> set[str]:
    """The project's modules that ``name`` imports, at the top or inside a function: ``from a.b import c``
    counts a.b.c when it is a module, else a.b."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        for t in targets:
            while t and t not in modules:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph``, as the modules around it, or None."""
    state: dict[str, int] = {}  # 1 on the path, 2 done
    path: list[str] = []

    def visit(v):
        state[v] = 1
        path.append(v)
        for w in sorted(graph[v]):
            if state.get(w) == 1:
                return path[path.index(w) :] + [w]
            if w not in state and (found := visit(w)):
                return found
        state[v] = 2
        path.pop()
        return None

    for v in sorted(graph):
        if v not in state and (found := visit(v)):
            return found
    return None


def test_cycle_finder_finds_a_planted_circle():
    """The finder itself: a three-module circle is found and named, a chain is not one."""
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_no_import_circles():
    modules = _modules()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    cycle = _cycle(graph)
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_files_and_functions_are_small():
    too_long = []
    for path in _modules().values():
        source = path.read_text()
        tree = ast.parse(source)
        functions = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]
        if source.count("\n") > MAX_FILE_LINES:
            too_long.append(f"{path.relative_to(ROOT)}: {source.count(chr(10))} lines")
        for f in functions:
            lines = f.end_lineno - f.lineno + 1
            if lines > MAX_FUNCTION_LINES:
                too_long.append(f"{path.relative_to(ROOT)}:{f.lineno} {f.name}: {lines} lines")
    assert not too_long, "; ".join(too_long)


#: The docs pages the benchmarks and the effectivity command write, with the commit they ran at.
GENERATED_DOCS = ("benchmarks.md", "effectivity.md")
#: A page is one concept, read in one sitting.
MAX_DOC_BYTES = 15 * 1024
#: A commit hash: 7 to 40 hexadecimal digits with a letter and a digit among them, standing alone.
COMMIT = r"(?<![\w.])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?!\w|\.\d)"


def test_the_docs_guide_and_do_not_log():
    """docs/ is a page per concept, each under 15 KB, and holds no commit hash but in the pages the
    commands write: the history of measurements lives in git and in those files (docs/models.md was a
    diary of 35 commits and 29 KB). Every docs page the code and the docs cite exists."""
    import re

    docs = ROOT / "docs"
    over = [f"{p.name}: {p.stat().st_size} bytes" for p in docs.glob("*.md") if p.stat().st_size > MAX_DOC_BYTES]
    assert not over, "pages over 15 KB: " + "; ".join(over)
    hashes = [
        f"{p.name}: {m.group(0)}"
        for p in docs.glob("*.md")
        if p.name not in GENERATED_DOCS
        for m in re.finditer(COMMIT, p.read_text())
    ]
    assert not hashes, "commit hashes in prose pages: " + "; ".join(hashes)
    assert re.search(COMMIT, "measured at b1e5165.") and not re.search(COMMIT, "0.0999999 and 1e5 and decade")
    sources = [*docs.glob("*.md"), ROOT / "README.md", *(ROOT / "tests").rglob("*.py")]
    sources += [path for pkg in PACKAGES for path in (ROOT / pkg).rglob("*.py")]
    cited = {c for path in sources for c in re.findall(r"docs/([\w-]+\.md)", path.read_text())}
    missing = sorted(c for c in cited if not (docs / c).exists())
    assert not missing, "cited docs pages that do not exist: " + ", ".join(missing)


#: The floors of the house (docs/architecture.md), lowest first: a module imports its own floor and those
#: below, never one above. Between the packages: realtime imports none of the others; meshes reads the
#: engine's geometry helpers and errors alone; reference reads the engine's pure material data alone.
PACKAGE_FLOORS = ("realtime", "meshes", "reference", "verification")
#: What a lower package may read of ``realtime``, by package.
FROM_REALTIME = {
    "meshes": ("realtime.errors", "realtime.geometry"),
    "reference": ("realtime.material",),
}
#: Inside verification: the shared modules (scene, cache, metrics, figures ...) at 0, then its wings;
#: ``inputs`` makes the seam's SceneInputs and stands on the engines' floor.
VERIFICATION_FLOORS = (("engines", "inputs"), ("runs",), ("studies",), ("bench",), ("report",), ("cli",))


def _floor(name: str) -> tuple[int, int]:
    """(the package's floor, the floor inside verification) of module ``name``."""
    parts = name.split(".")
    inner = 0
    if parts[0] == "verification" and len(parts) > 1:
        inner = next((k + 1 for k, wing in enumerate(VERIFICATION_FLOORS) if parts[1] in wing), 0)
    return PACKAGE_FLOORS.index(parts[0]), inner


def _upward(graph: dict[str, set[str]]) -> list[str]:
    """Every import of ``graph`` that goes up a floor, or reads more of realtime than its package may."""
    up = []
    for name, deps in sorted(graph.items()):
        for dep in sorted(deps):
            if _floor(dep) > _floor(name):
                up.append(f"{name} -> {dep}")
            allowed = FROM_REALTIME.get(name.split(".")[0])
            if allowed is not None and dep.startswith("realtime") and dep not in allowed:
                up.append(f"{name} -> {dep} (only {', '.join(allowed)})")
    return up


def test_the_floor_check_finds_a_planted_upward_import():
    assert _upward({"verification.runs.x": {"verification.studies.y"}}) == [
        "verification.runs.x -> verification.studies.y"
    ]
    assert _upward({"reference.a": {"realtime.models"}}) == ["reference.a -> realtime.models (only realtime.material)"]
    assert (
        _upward({"verification.cli.a": {"verification.runs.b", "meshes.io"}, "meshes.io": {"realtime.geometry"}}) == []
    )


def test_no_import_goes_up_a_floor():
    modules = _modules()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    up = _upward(graph)
    assert not up, "imports up a floor: " + "; ".join(up)
