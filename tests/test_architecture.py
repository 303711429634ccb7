"""The layout rules of docs/architecture.md, checked by parsing every import with `ast`.

Function-level imports count as much as module-level ones (the code imports heavy modules
lazily, inside functions). Each rule names the file and line that breaks it.
"""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

#: What the device side may import besides the standard library and itself.
DEVICE_THIRD_PARTY = {"numpy", "serial", "cbor2", "zstandard", "pygame"}

#: The host stages in pipeline order, and which earlier stages each may import.
#: evaluate and link both come after fit and never import each other.
STAGES = ("volume", "render", "fit", "evaluate", "link")
STAGE_MAY_IMPORT = {
    "volume": set(),
    "render": {"volume"},
    "fit": {"volume", "render"},
    "evaluate": {"volume", "render", "fit"},
    "link": {"volume", "render", "fit"},
}
#: Top-level host modules every stage may import (cross-cutting, no pipeline knowledge).
HOST_SHARED = {"host", "host.errors", "host.progress", "host.lazy", "host.shared_data"}

MAX_LINES = 1000
#: Modules longer than MAX_LINES, each with why it is still one file (its docstring says so
#: too; part 2 of issue 12 split the others); the list must stay exact.
LONG_MODULES = {
    "protocol/image.py": "the .ecs file format: its layout, writer and reader change together",
    "device_runtime/flash.py": "FlashStore: every method is a step of the one power-cut "
    "argument in its docstring (writer, formats, file seam and errors are modules of their own)",
    "protocol/messages.py": "the catalogue of message declarations the golden lines and "
    "docs/protocol.md are checked against (the records machinery is protocol/records.py)",
}


def _modules(package: str) -> list[Path]:
    return sorted((REPO / package).rglob("*.py"))


def _name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path``, function-level too."""
    return _imports_source(path.read_text(), path)


def _imports_source(source: str, path: Path) -> list[tuple[int, str]]:
    out = []
    tree = ast.parse(source, filename=str(path))
    package = _name(path) if path.name == "__init__.py" else _name(path).rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing package
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join([*base, node.module] if node.module else base)
            else:
                module = node.module or ""
            out.append((node.lineno, module))
    return out


def _stage(module: str) -> str | None:
    """``"render"`` for ``host.render`` or ``host.render.camera``; None elsewhere."""
    parts = module.split(".")
    if len(parts) >= 2 and parts[0] == "host" and parts[1] in STAGES:
        return parts[1]
    return None


def _where(path: Path, line: int) -> str:
    return f"{path.relative_to(REPO)}:{line}"


# ----------------------------------------------------------------------------- device side


@pytest.mark.parametrize("package", ["protocol", "device_runtime"])
def test_device_side_imports_only_stdlib_and_its_dependencies(package):
    allowed_first_party = {"protocol"} if package == "device_runtime" else set()
    allowed = set(sys.stdlib_module_names) | DEVICE_THIRD_PARTY | {package} | allowed_first_party
    bad = [
        f"{_where(path, line)} imports {module}"
        for path in _modules(package)
        for line, module in _imports(path)
        if module.split(".")[0] not in allowed and module != "__future__"
    ]
    assert not bad, f"{package}/ may import only stdlib, {sorted(DEVICE_THIRD_PARTY)}" + (
        " and protocol" if allowed_first_party else ""
    ) + ":\n" + "\n".join(bad)


def test_protocol_imports_neither_host_nor_device_runtime():
    bad = [
        f"{_where(path, line)} imports {module}"
        for path in _modules("protocol")
        for line, module in _imports(path)
        if module.split(".")[0] in ("host", "device_runtime")
    ]
    assert not bad, "\n".join(bad)


def test_device_runtime_never_imports_host():
    bad = [
        f"{_where(path, line)} imports {module}"
        for path in _modules("device_runtime")
        for line, module in _imports(path)
        if module.split(".")[0] == "host"
    ]
    assert not bad, "\n".join(bad)


# ----------------------------------------------------------------------------- host stages


@pytest.mark.parametrize("stage", STAGES)
def test_host_stage_imports_only_earlier_stages(stage):
    bad = []
    for path in _modules(f"host/{stage}"):
        for line, module in _imports(path):
            if module.split(".")[0] != "host":
                continue
            target = _stage(module)
            if target == stage or module in HOST_SHARED:
                continue
            if target is None or target not in STAGE_MAY_IMPORT[stage]:
                bad.append(f"{_where(path, line)} imports {module}")
    assert not bad, (
        f"host/{stage}/ may import host stages {sorted(STAGE_MAY_IMPORT[stage])} and "
        f"{sorted(HOST_SHARED)} only (never the CLI, demo or a later stage):\n" + "\n".join(bad)
    )


def test_shared_host_modules_import_no_stage():
    bad = [
        f"{_where(REPO / 'host' / (name.split('.')[-1] + '.py'), line)} imports {module}"
        for name in sorted(HOST_SHARED - {"host"})
        for line, module in _imports(REPO / "host" / (name.split(".")[-1] + ".py"))
        if _stage(module) or module.startswith(("host.commands", "host.cli", "host.demo"))
    ]
    assert not bad, "\n".join(bad)


def test_every_stage_has_a_documented_package_whose_names_resolve():
    from host.lazy import defining_modules

    for stage in STAGES:
        package = importlib.import_module(f"host.{stage}")
        doc = package.__doc__ or ""
        assert "May import" in doc, f"host/{stage}/__init__.py docstring lacks its import rule"
        assert len(package.__all__) == len(set(package.__all__)), f"host.{stage}: a name twice"
        owners = defining_modules(f"host.{stage}", package.__all__)
        for name, modules in owners.items():
            assert len(modules) == 1, f"host.{stage}.{name} is defined in {modules or 'no module'}"
            defining = importlib.import_module(f"host.{stage}.{modules[0]}")
            # also catches a submodule named like a function it exports (it would shadow it)
            assert getattr(package, name) is getattr(defining, name), f"host.{stage}.{name}"


def test_stage_package_import_is_lazy():
    # `eigencast --help` imports every command; a stage package must not pull in numba.
    import subprocess

    code = (
        "import sys, host.volume, host.render, host.fit, host.evaluate, host.link\n"
        "from host.render import Camera, CinemaDB\n"
        "print('numba' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=REPO)
    assert out.stdout.strip() == "False"


# ----------------------------------------------------------------------------- size


def test_no_module_over_1000_lines_unless_listed():
    long = {
        str(path.relative_to(REPO)): len(path.read_text().splitlines())
        for package in ("host", "protocol", "device_runtime")
        for path in _modules(package)
    }
    over = {path for path, n in long.items() if n > MAX_LINES}
    unlisted = sorted(over - set(LONG_MODULES))
    assert not unlisted, f"over {MAX_LINES} lines: {unlisted}; split it or list it with a reason"
    stale = sorted(set(LONG_MODULES) - over)
    assert not stale, f"listed as long but no longer over {MAX_LINES} lines: {stale}"
    for path in LONG_MODULES:  # and the module itself says why it is one idea
        doc = ast.get_docstring(ast.parse((REPO / path).read_text())) or ""
        assert "stays one file" in doc, f"{path}: its docstring must say why it stays one file"


def test_the_import_parser_sees_function_level_and_relative_imports():
    # the rules above are only as good as this parser: a lazy import inside a method counts
    settings = REPO / "host" / "render" / "settings.py"
    top_level = {n.lineno for n in ast.parse(settings.read_text()).body}
    lazy = [(line, m) for line, m in _imports(settings) if m == "host.render.raycast"]
    assert lazy and all(line not in top_level for line, _ in lazy)
    fake = REPO / "host" / "render" / "__init__.py"
    assert (1, "host.render.camera") in [
        (line, m) for line, m in _imports_source("from .camera import Camera\n", fake)
    ]


# ----------------------------------------------------------------------------- circles


def _host_import_graph() -> dict[str, set[str]]:
    """Module -> the host modules it imports (function-level too); ``from host.link import
    serving`` is an edge to ``host.link.serving``, ``from host.link.serving import serve`` one
    to ``host.link.serving``."""
    paths = {_name(path): path for path in _modules("host")}
    graph: dict[str, set[str]] = {name: set() for name in paths}
    for name, path in paths.items():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                targets = [f"{node.module}.{alias.name}" for alias in node.names]
            else:
                continue
            for target in targets:
                while target and target not in paths:  # a name in a module: the module
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _folder(module: str) -> str:
    """The folder of host/ a module's file is in: ``host/link`` for ``host.link.serving``,
    ``host`` for ``host.cluster`` (a package's ``__init__`` is in its own folder)."""
    path = REPO / Path(*module.split("."))
    return str((path if path.is_dir() else path.parent).relative_to(REPO))


def test_no_import_circle_crosses_a_folder_of_host():
    # a circle within one folder is one idea split into files; one across folders means a
    # lower layer reaches up (e.g. the cluster's workers into the command line)
    crossing = [c for c in _circles(_host_import_graph()) if len({_folder(m) for m in c}) > 1]
    assert not crossing, "import circles across folders of host/ (move what both need below "\
        "both):\n" + "\n".join(" <-> ".join(c) for c in crossing)


def test_the_circle_finder_sees_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _circles(graph) == [["a", "b", "c"]]
    assert _folder("host.link.serving") == "host/link" and _folder("host.cluster") == "host"
    assert _folder("host.link") == "host/link"
