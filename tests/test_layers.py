"""The layering of the package docstring (spherejax/__init__.py), enforced on the source, and the
structure rules beside it: no import cycle, no module over `MAX_LINES` lines.

Every import in spherejax/ and hw/ is read from the syntax tree, those inside functions included
(a lazy import is still a dependency); only imports under `if TYPE_CHECKING:` are left out, since
they never run. A module may import modules of its own layer or of the layers below it, and no
chain of imports may lead from a module back to itself, within a layer too: a cycle leaves each of
its modules half-initialised while another runs (hidden today by a lazy import, broken by the next
top-level one), and none can be read, tested or moved without the others. hw/, the instrument
package, installs as `spherejax_hw` and uses spherejax; spherejax never imports it (its `acquire`
command reaches the command line through an entry point).
"""

import ast
import importlib.metadata
import pathlib
import tomllib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

KERNELS, WORKFLOWS, FILES = 1, 2, 3
LAYERS = {
    **dict.fromkeys(
        ["colorimetry", "flatfield", "polynomial", "estimation", "wiener_estimation", "quality", "calibration", "equations",
         "pipeline", "uncertainty", "consistency",
         "markov", "angles", "_engine", "pixel_constants", "correction_result", "grid", "spectra", "jsontext", "noise_document",
         "noise_bands", "number_text", "labelled", "_checks", "atomic_files", "band_resampling"], KERNELS),
    **dict.fromkeys(
        ["calibrate", "calibrate_registration", "evaluate", "study", "simulate", "stripwise", "measurement", "monte_carlo",
         "simulated_targets", "kubelka_munk", "target_families", "simulated_instrument", "simulated_layout", "simulated_rendering", "band_geometry", "band_registration", "sphere_radiosity", "textile_brdf", "twin", "figures"], WORKFLOWS),
    **dict.fromkeys(["io", "measurement_files", "archive", "cluster", "interrupt", "console", "cli", "__main__", "hw",
                     "viewer"],
                    FILES),
}
#: The installed name of the package in the folder hw/.
HW_PACKAGE = "spherejax_hw"


def sources():
    """(module path as a dotted name, as installed, file) of every spherejax and hw source but
    the package's own __init__ (the public facade, which re-exports from every layer)."""
    for file in sorted([*(ROOT / "spherejax").rglob("*.py"), *(ROOT / "hw").rglob("*.py")]):
        parts = file.relative_to(ROOT).with_suffix("").parts
        if parts == ("spherejax", "__init__"):
            continue
        if parts[0] == "hw":
            parts = (HW_PACKAGE, *parts[1:])
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), file


def imported_modules(module: str, file: pathlib.Path) -> set[str]:
    """Dotted names of everything `file` imports at run time (relative imports resolved)."""
    tree = ast.parse(file.read_text(encoding="utf-8"))
    package = module.split(".") if file.name == "__init__.py" else module.split(".")[:-1]
    type_checking_only = {
        id(inner)
        for guard in ast.walk(tree) if isinstance(guard, ast.If) and "TYPE_CHECKING" in ast.unparse(guard.test)
        for statement in guard.body for inner in ast.walk(statement)
    }
    found = set()
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in type_checking_only:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
            continue
        base = package[: len(package) - node.level + 1] if node.level else []
        prefix = ".".join([*base, *(node.module.split(".") if node.module else [])])
        if node.module is not None:
            found.add(prefix)  # `from .grid import N`: depends on spherejax.grid
        for alias in node.names:
            # `from . import io`, `from .io import atomic`: a module, if the name is one.
            found.add(f"{prefix}.{alias.name}")
    return found


def layer_of(name: str) -> tuple[str, int] | None:
    """(the layered unit, its layer) of a dotted module name in spherejax or hw, else None."""
    parts = name.split(".")
    if parts[0] in ("hw", HW_PACKAGE):  # `hw`: the folder's own name, which must not be imported
        return "hw", LAYERS["hw"]
    if parts[0] != "spherejax" or len(parts) == 1:
        return None
    return parts[1], LAYERS.get(parts[1], 0)


def import_graph() -> dict[str, set[str]]:
    """module -> the modules of spherejax and hw it imports (`sources`), each import taken to the
    longest dotted prefix that is a module (`from .estimation import wiener` is an edge to the
    package spherejax.estimation; `from .io import atomic`, to spherejax.io.atomic). The facade,
    spherejax/__init__.py, is no node: `from . import _checks` runs it, but it is the re-export of
    every layer, not a dependency of the module importing its sibling."""
    found = dict(sources())
    graph = {}
    for module, file in found.items():
        edges = set()
        for name in imported_modules(module, file):
            while name and name not in found:
                name = name.rpartition(".")[0]
            if name and name != module:
                edges.add(name)
        graph[module] = edges
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The cycles of `graph` (node -> the nodes it imports): its strongly connected components
    of more than one node, and any node that imports itself, each sorted, in sorted order.
    Tarjan's algorithm, written without recursion (the graph has a few hundred nodes, chains of
    imports as deep as the package)."""
    index, low, on_stack, stack, cycles = {}, {}, set(), [], []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            successor = next(successors, None)
            if successor is not None:
                if successor not in index:
                    index[successor] = low[successor] = len(index)
                    stack.append(successor)
                    on_stack.add(successor)
                    work.append((successor, iter(sorted(graph.get(successor, ())))))
                elif successor in on_stack:
                    low[node] = min(low[node], index[successor])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1 or node in graph.get(node, ()):
                    cycles.append(sorted(component))
    return sorted(cycles)


#: No source of spherejax or hw, Python or the fused kernel's C++, may be longer: a file longer
#: than this has more than one job (split it by job) or is a changelog in comments.
MAX_LINES = 700
#: The sources `MAX_LINES` applies to, by the end of their names, under spherejax/ and hw/.
LIMITED_SOURCES = (".py", ".cc", ".cpp", ".h", ".hpp")


def over_long(files) -> list[str]:
    """"path: N lines" of each of `files` longer than `MAX_LINES` lines."""
    found = []
    for file in files:
        with open(file, encoding="utf-8") as text:
            lines = sum(1 for _ in text)
        if lines > MAX_LINES:
            found.append(f"{file.relative_to(ROOT) if file.is_relative_to(ROOT) else file}: {lines} lines")
    return found


def test_the_import_graph_has_no_cycle():
    cycles = import_cycles(import_graph())
    assert cycles == [], "import cycles (each a set of modules that import each other, through lazy imports too): " + "; ".join(
        " <-> ".join(cycle) for cycle in cycles)


def test_the_cycle_finder_finds_what_it_must():
    """The check above can fail: a two-module cycle, a longer one, a module importing itself,
    and no cycle where imports only point one way."""
    graph = {"a": {"b"}, "b": {"a", "c"}, "c": {"d"}, "d": {"e"}, "e": {"c"}, "f": {"f"}, "g": {"a", "c"}}
    assert import_cycles(graph) == [["a", "b"], ["c", "d", "e"], ["f"]]
    assert import_cycles({"a": {"b", "c"}, "b": {"c"}, "c": set()}) == []
    deep = {f"m{i}": {f"m{i + 1}"} for i in range(5000)} | {"m5000": {"m0"}}  # no recursion limit
    assert import_cycles(deep) == [sorted(deep)]


def test_the_graph_holds_the_imports():
    """Edges go to the module a name lies in, lazy imports included; the facade is no node."""
    graph = import_graph()
    assert "spherejax" not in graph and "spherejax.estimation.estimator" in graph
    assert "spherejax.estimation.estimator" in graph["spherejax.estimation.kernel_residual"]
    assert "spherejax.estimation" in graph["spherejax.uncertainty"]  # `from .estimation import EstimatorCovariance`
    assert all(not edge.startswith("spherejax_hw") for module, edges in graph.items()
               if module.startswith("spherejax.") for edge in edges)


def test_no_source_is_over_the_line_limit():
    files = sorted(file for root in ("spherejax", "hw") for file in (ROOT / root).rglob("*")
                   if file.is_file() and file.name.endswith(LIMITED_SOURCES))
    assert any(file.suffix == ".cc" for file in files) and any(file.suffix == ".py" for file in files)
    long = over_long(files)
    assert long == [], f"over {MAX_LINES} lines (split by job): {long}"


def test_the_line_limit_can_fail(tmp_path):
    (tmp_path / "long.py").write_text("x = 1\n" * (MAX_LINES + 1))
    (tmp_path / "at.cc").write_text("int x;\n" * MAX_LINES)
    assert over_long(sorted(tmp_path.iterdir())) == [f"{tmp_path / 'long.py'}: {MAX_LINES + 1} lines"]


def test_every_module_has_a_layer():
    units = {layer_of(module)[0] for module, _ in sources()}
    assert sorted(units - set(LAYERS)) == [], "a new module: put it in a layer here and in the package docstring"
    assert sorted(set(LAYERS) - units) == []  # names that no longer exist


@pytest.mark.parametrize("module, file", list(sources()), ids=lambda x: x if isinstance(x, str) else "")
def test_imports_go_down_the_layers(module, file):
    unit, layer = layer_of(module)
    upward = []
    for name in sorted(imported_modules(module, file)):
        target = layer_of(name)
        if target is None or target[0] == unit:
            continue
        if target[0] == "hw" and unit != "hw":
            upward.append(f"{name} (the instrument package: it depends on spherejax, not the reverse)")
            continue
        if target[1] > layer:
            upward.append(f"{name} (layer {target[1]}, above {unit}'s {layer})")
    assert upward == [], f"{module} imports upward: {upward}"


def test_the_reader_sees_what_it_must(tmp_path):
    """The checks above can fail: an upward import, a lazy one and a TYPE_CHECKING one."""
    lazy, guarded, nested = tmp_path / "lazy.py", tmp_path / "guarded.py", tmp_path / "nested.py"
    lazy.write_text("def f():\n    from . import io\n")
    guarded.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import io\nelse:\n    import json\n")
    nested.write_text("from .. import grid\nfrom . import frames\nfrom .sessions import Session\n")
    assert imported_modules("spherejax.simulated_targets", lazy) == {"spherejax.io"}
    assert imported_modules("spherejax.stripwise", guarded) == {"typing", "typing.TYPE_CHECKING", "json"}
    assert imported_modules("spherejax.io.atomic", nested) == {
        "spherejax.grid", "spherejax.io.frames", "spherejax.io.sessions", "spherejax.io.sessions.Session"}


def test_no_test_module_imports_another():
    """What tests share lives in support modules (tests/helpers.py, batch_support.py,
    hw/support.py, hw/profiles.py, robustness/catalogue.py) and tests/conftest.py, never in
    another test file."""
    tests = ROOT / "tests"
    importing = []
    for file in sorted(tests.rglob("*.py")):
        module = ".".join(file.relative_to(ROOT).with_suffix("").parts)
        for name in imported_modules(module, file):
            if name.startswith("tests.") and name.rsplit(".", 1)[-1].startswith("test_"):
                importing.append(f"{file.relative_to(ROOT)} imports {name}")
    assert importing == []


def test_hw_is_imported_by_its_installed_name():
    """`import hw` would find whatever other package of that name comes first on the path."""
    by_folder = []
    for folder in ("spherejax", "hw", "tests", "benchmarks"):
        for file in sorted((ROOT / folder).rglob("*.py")):
            parts = file.relative_to(ROOT).with_suffix("").parts
            module = ".".join((HW_PACKAGE, *parts[1:]) if folder == "hw" else parts)
            by_folder += [f"{file.relative_to(ROOT)}: {name}" for name in imported_modules(module, file)
                          if name == "hw" or name.startswith("hw.")]
    assert by_folder == []


def test_every_package_folder_is_installed():
    """pyproject.toml lists the packages by hand (hw/ installs under another name): a new package
    folder missing from the list would be left out of a wheel."""
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    folders = {setuptools["package-dir"].get(name, name.replace(".", "/")): name for name in setuptools["packages"]}
    on_disk = {str(init.parent.relative_to(ROOT)) for root in ("spherejax", "hw") for init in (ROOT / root).rglob("__init__.py")}
    assert set(folders) == on_disk
    assert setuptools["package-dir"] == {HW_PACKAGE: "hw"}


def test_the_acquire_command_comes_from_the_instrument_package():
    from spherejax import cli

    (entry_point,) = [e for e in importlib.metadata.entry_points(group=cli.COMMAND_ENTRY_POINTS) if e.name == "acquire"]
    assert entry_point.value == f"{HW_PACKAGE}.command:add_command"
    parser = cli.build_parser()
    args = parser.parse_args(["acquire", "--profile", "p.toml", "-o", "s", "--emulate"])
    assert args.run.__module__ == f"{HW_PACKAGE}.command" and args.emulate and args.profile == "p.toml"
