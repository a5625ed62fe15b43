"""The package rules of shared/ARCHITECTURE.md, read from the source with `ast`.

Every import counts, at module level and inside functions (a lazy import still runs): the
production packages import nothing from the studio (`avatar_core.synth`), `protocol` imports
none of ours, the engine imports no server, client or web framework, and the module-level
import graph of our packages has no circle. Exceptions are listed with the reason they stand.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("avatar_core", "server", "client", "protocol")
STUDIO = "avatar_core.synth"
# Engine modules that are front ends to the studio, not production paths (issue 15: "the studio
# CLI and the demo-avatar builder may keep using the studio").
STUDIO_FRONT_ENDS = ("avatar_core.cli", "avatar_core.demo")
# The studio's one entry point: what production needs the studio to make (the synthetic
# body-model family, the trained demo avatar) it asks of this module, whose imports of the
# studio are lazy. Production reaches it only at start-up, from the modules listed here.
STUDIO_ENTRY = "avatar_core.studio_entry"
STUDIO_ENTRY_CALLERS = {
    "avatar_core.body.model_paths":
        "the resolver's last resort: the synthetic family, generated on first use",
    "server.registry":
        "the server's start-up demo avatar, when configured as 'trained'",
    "server.jobs.demo_build":
        "the trained demo avatar, built in the background from start-up when not cached",
}
STUDIO_ENTRY_REASON = (
    "the studio's one entry point (STUDIO_ENTRY): the synthetic family is written by the "
    "studio, the trained demo avatar built by the demo-avatar builder (issue 15 lets it use "
    "the studio); lazy, so importing the entry never loads the studio")
# (importer, imported module or package) pairs allowed to break a rule, and why.
ALLOWED = {
    (STUDIO_ENTRY, STUDIO): STUDIO_ENTRY_REASON,
    (STUDIO_ENTRY, "avatar_core.demo"): STUDIO_ENTRY_REASON,
    ("avatar_core.cli", "server.cli"):
        "`telesplat serve` is dispatched to the server's CLI by a lazy import",
}
# Lazy (function-level) imports that close circles, and why each stands: without them the
# lazy graph has none. Remove an entry when no circle runs through it; the module-level
# graph has none and gets none.
KNOWN_LAZY_CYCLE_EDGES: dict[tuple[str, str], str] = {
    ("avatar_core.body.model_paths", STUDIO_ENTRY):
        "the resolver's last resort asks the studio entry, whose studio (the model writer, the "
        "demo-avatar builder's capture and trainer) resolves body models in turn",
}
WEB_FRAMEWORKS = ("fastapi", "starlette", "uvicorn", "server", "client")


@dataclass(frozen=True)
class Import:
    importer: str
    target: str  # dotted name as written (resolved when relative); a module or a module.attr
    line: int
    module_level: bool


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _source_files() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if "__pycache__" not in path.parts:
                out[_module_name(path)] = path
    return out


MODULES = _source_files()


def _resolve(importer: str, is_package: bool, level: int, module: str | None) -> str:
    if level == 0:
        return module or ""
    base = importer.split(".") if is_package else importer.split(".")[:-1]
    base = base[:len(base) - (level - 1)]
    return ".".join([*base, module] if module else base)


class _Collector(ast.NodeVisitor):
    def __init__(self, name: str, is_package: bool) -> None:
        self.name, self.is_package = name, is_package
        self.depth = 0  # > 0 inside a function body
        self.found: list[Import] = []

    def _function(self, node: ast.AST) -> None:
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _function

    def visit_If(self, node: ast.If) -> None:
        """`if TYPE_CHECKING:` imports never run (annotations only): no edge of the graph."""
        test = node.test
        name = test.id if isinstance(test, ast.Name) else getattr(test, "attr", None)
        if name != "TYPE_CHECKING":
            self.generic_visit(node)
            return
        for child in node.orelse:
            self.visit(child)

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self.found.append(Import(self.name, alias.name, node.lineno, self.depth == 0))

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        base = _resolve(self.name, self.is_package, node.level, node.module)
        for alias in node.names:
            target = base if alias.name == "*" else f"{base}.{alias.name}"
            self.found.append(Import(self.name, target, node.lineno, self.depth == 0))


def _imports() -> list[Import]:
    out = []
    for name, path in MODULES.items():
        collector = _Collector(name, path.name == "__init__.py")
        collector.visit(ast.parse(path.read_text(), filename=str(path)))
        out.extend(collector.found)
    return out


IMPORTS = _imports()


def _within(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def _module_of(target: str) -> str | None:
    """Our module that an import target names (`pkg.mod.attr` -> `pkg.mod`); None if not ours."""
    parts = target.split(".")
    for end in range(len(parts), 0, -1):  # bounded by the dotted name's length
        if ".".join(parts[:end]) in MODULES:
            return ".".join(parts[:end])
    return None


def _violations(importers, forbidden) -> list[str]:
    out = []
    for imp in IMPORTS:
        if not importers(imp.importer) or not any(_within(imp.target, f) for f in forbidden):
            continue
        allowed = any(_within(imp.target, dst) for src, dst in ALLOWED if src == imp.importer)
        if not allowed:
            out.append(f"{imp.importer}:{imp.line} imports {imp.target}")
    return out


def _production(name: str) -> bool:
    if _within(name, "server"):
        return True
    return (_within(name, "avatar_core") and not _within(name, STUDIO)
            and name not in STUDIO_FRONT_ENDS)


def test_the_rules_see_the_code():
    # A scan that found nothing would pass every rule.
    assert {"avatar_core.pipeline", "avatar_core.body.model_paths", "server.app",
            "protocol.codec", "client.stream", "avatar_core.motion.library"} <= set(MODULES)
    assert any(i.target == "avatar_core.synth.model_writer.ensure_models" and not i.module_level
               for i in IMPORTS)  # function-level imports are seen


def test_production_packages_do_not_import_the_studio():
    assert _violations(_production, (STUDIO,)) == []


def test_production_reaches_the_studio_front_ends_only_where_listed():
    assert _violations(_production, STUDIO_FRONT_ENDS) == []


def test_allowed_imports_stay_lazy():
    for imp in IMPORTS:
        if any(src == imp.importer and _within(imp.target, dst) for src, dst in ALLOWED):
            assert not imp.module_level, f"{imp.importer}:{imp.line} must import lazily"


def test_production_reaches_the_studio_entry_only_at_start_up():
    reach = [imp for imp in IMPORTS
             if _module_of(imp.target) == STUDIO_ENTRY and _production(imp.importer)
             and imp.importer != STUDIO_ENTRY]
    assert {imp.importer for imp in reach} == set(STUDIO_ENTRY_CALLERS)
    eager = [f"{imp.importer}:{imp.line}" for imp in reach if imp.module_level]
    assert eager == [], f"must import {STUDIO_ENTRY} lazily: {eager}"


def test_no_module_imports_the_renderers_private_names():
    # what two render entries share is public in one module (render.checks), not borrowed
    found = [f"{i.importer}:{i.line} imports {i.target}" for i in IMPORTS
             if _within(i.target, "avatar_core.render") and _module_of(i.target) != i.target
             and i.target.rsplit(".", 1)[-1].startswith("_")
             and not i.target.rsplit(".", 1)[-1].startswith("__")]
    assert found == []


def test_protocol_imports_none_of_ours_nor_torch():
    forbidden = ("avatar_core", "server", "client", "torch")
    assert _violations(lambda n: _within(n, "protocol"), forbidden) == []


def test_engine_imports_no_server_client_or_web_framework():
    assert _violations(lambda n: _within(n, "avatar_core"), WEB_FRAMEWORKS) == []


def test_client_imports_no_server():
    assert _violations(lambda n: _within(n, "client"), ("server",)) == []


def test_client_reaches_the_engine_only_lazily_for_the_local_tracker():
    # the remote tracker fits on this machine (avatar_core.track, its body models resolved by
    # avatar_core.body there); nothing else of the engine, and never at import time
    found = [f"{i.importer}:{i.line} imports {i.target}" for i in IMPORTS
             if _within(i.importer, "client") and _within(i.target, "avatar_core")
             and (i.module_level or not _within(i.target, "avatar_core.track"))]
    assert found == []


def test_client_has_no_torch_at_import_time():
    code = ("import sys, client, client.cli, client.stream, client.rest, client.images\n"
            "assert 'torch' not in sys.modules, 'torch imported'\n"
            "assert 'avatar_core' not in sys.modules, 'avatar_core imported'\n")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr


def _module_graph(lazy: bool) -> dict[str, set[str]]:
    """Module -> our modules it imports: at module level, and with `lazy` inside functions."""
    graph: dict[str, set[str]] = {name: set() for name in MODULES}
    for imp in IMPORTS:
        target = _module_of(imp.target)
        if (imp.module_level or lazy) and target is not None and target != imp.importer:
            graph[imp.importer].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: set[frozenset[str]] = set()
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:  # each module enters once, each edge is followed once
            node, edges = work[-1]
            nxt = next(edges, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.add(frozenset(component))
    return found


def test_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == {frozenset("abc")}
    assert _cycles({"a": {"b"}, "b": set()}) == set()


def test_no_import_cycle_between_modules():
    cycles = [sorted(c) for c in _cycles(_module_graph(lazy=False))]
    assert cycles == [], f"import cycles at module level: {cycles}"


def _reaches(graph: dict[str, set[str]], start: str, goal: str) -> bool:
    seen, todo = {start}, [start]
    while todo:  # each module once
        for nxt in graph[todo.pop()] - seen:
            if nxt == goal:
                return True
            seen.add(nxt)
            todo.append(nxt)
    return False


def test_no_new_cycle_through_lazy_imports():
    graph = _module_graph(lazy=True)
    for importer, imported in KNOWN_LAZY_CYCLE_EDGES:
        graph[importer].discard(imported)
    new = [sorted(c) for c in _cycles(graph)]
    assert new == [], f"import cycles through function-level imports: {new}"


def test_known_lazy_cycle_edges_still_close_a_cycle():
    graph = _module_graph(lazy=True)
    gone = [edge for edge in KNOWN_LAZY_CYCLE_EDGES
            if edge[1] not in graph[edge[0]] or not _reaches(graph, edge[1], edge[0])]
    assert gone == [], f"no cycle through these, remove from KNOWN_LAZY_CYCLE_EDGES: {gone}"


# -- one stream path (issue 24) -------------------------------------------------------------

# The modules the server's root may hold: the app, its settings, auth, avatars, metrics and
# the cluster connection. Streaming (gate, session, transports, scene, scheduler, batching,
# encoders, drive, tracking) lives in server/stream/.
SERVER_ROOT = {"server", "server.__main__", "server.app", "server.auth", "server.cli",
               "server.cluster", "server.config", "server.context", "server.dependencies",
               "server.logsafe", "server.loop_watch", "server.metrics", "server.private",
               "server.quotas",
               "server.registry", "server.sqlite", "server.uploads"}
BUILT_ON_STREAM = ("server.rooms", "server.webrtc", "server.cluster_render")
ENCODERS = "server.stream.encoders"
# Where a codec may be named outside the encoders: the protocol (its codec list) and WebRTC's
# own video codecs, which aiortc negotiates with the browser and encodes per peer (they never
# reach a scene).
CODEC_NAMERS = ("protocol", "server.webrtc.encoders", "server.webrtc.negotiate")


def test_the_server_root_holds_no_streaming_module():
    root = {name for name in MODULES if name.count(".") <= 1 and _within(name, "server")
            and not any(_within(name, f"server.{pkg}") for pkg in (
                "stream", "rooms", "webrtc", "cluster_render", "jobs", "routers"))}
    assert root == SERVER_ROOT


def test_stream_imports_nothing_that_builds_on_it():
    found = [f"{i.importer}:{i.line} imports {i.target}" for i in IMPORTS
             if _within(i.importer, "server.stream")
             and any(_within(i.target, pkg) for pkg in BUILT_ON_STREAM)]
    assert found == []


def _stateful_codecs() -> set[str]:
    from server.stream.encoders import STATEFUL

    assert STATEFUL, "the rule below would check nothing"
    return set(STATEFUL)


def test_only_the_encoders_know_a_codec_is_stateful():
    """Outside server/stream/encoders nobody imports an encoder's stream state, nor names a
    stateful codec: the scene, the frame sharing and Ray pass codecs through as names."""
    stateful = _stateful_codecs()
    private = (f"{ENCODERS}.h264", f"{ENCODERS}.STATEFUL", f"{ENCODERS}.H264Stream",
               f"{ENCODERS}.H264Encoder")
    found = [f"{i.importer}:{i.line} imports {i.target}" for i in IMPORTS
             if _within(i.importer, "server") and not _within(i.importer, ENCODERS)
             and any(_within(i.target, p) for p in private)]
    for name, path in MODULES.items():
        if (not _within(name, "server") or _within(name, ENCODERS)
                or any(_within(name, c) for c in CODEC_NAMERS)):
            continue
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Constant) and node.value in stateful:
                found.append(f"{name}:{node.lineno} names the codec {node.value!r}")
    assert found == []
