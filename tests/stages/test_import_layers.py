"""The stages import each other along the DAG: the module graph of ``stages/`` (every import statement,
including those inside functions) has no cycle, and the inference path never imports torch."""

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def module_graph() -> dict[str, set[str]]:
    """{module: the stages modules its import statements name} over every file under stages/."""
    modules = {}
    for path in (REPO / "stages").rglob("*.py"):
        parts = path.relative_to(REPO).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                targets |= {f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names}
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def test_the_stages_module_graph_has_no_cycle():
    graph, state, cycles = module_graph(), {}, []

    def visit(node, trail):
        state[node] = "open"
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                cycles.append(trail[trail.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, [*trail, nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)
    assert "stages.inference.runtime" in graph["stages.evaluate.methods"]  # the graph does see imports


def test_inference_never_imports_torch():
    code = "import stages.inference.infer, sys; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)


def test_the_detector_stage_key_holds_no_relation_code():
    """Training the detector does not depend on the relation network: a change to the relation (or to the
    inference runtime, which imports it) must not invalidate a 15-minute detector training in the cache."""
    from pipeline.codeversion import code_version

    files = code_version("stages.detector.stage", frozenset({"stages", "pipeline"})).files
    assert "stages/detector/stage.py" in files
    assert not [f for f in files if f.startswith(("stages/relation/", "stages/inference/", "stages/export/"))]
