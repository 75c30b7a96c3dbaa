"""Imports follow the layers of docs/design.md §2: ``pipeline`` (the engine) and ``deepword`` (the library) import
neither each other nor ``stages``; a DAG node's package imports only packages upstream of it in conf/config.yaml;
neither the module graph (every import statement, including those inside functions) nor the package graph has a
cycle; and the inference path never imports torch."""

import ast
import subprocess
import sys
from pathlib import Path

from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[2]
ROOTS = ("deepword", "stages", "pipeline")


def modules() -> dict[str, Path]:
    found = {}
    for root in ROOTS:
        for path in (REPO / root).rglob("*.py"):
            parts = path.relative_to(REPO).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def module_graph() -> dict[str, set[str]]:
    """{module: the project modules its import statements name} over every file of the project's packages."""
    mods = modules()
    graph = {}
    for name, path in mods.items():
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
                targets |= {f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names}
        graph[name] = {t for t in targets if t in mods and t != name}
    return graph


def package_of(module: str) -> str:
    """``deepword`` and ``pipeline`` are one package each; ``stages.<name>`` (a DAG node's package, training,
    inference, tables) or the module ``stages.cli``."""
    parts = module.split(".")
    return parts[0] if parts[0] != "stages" else ".".join(parts[:2])


def package_graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for module, targets in module_graph().items():
        graph.setdefault(package_of(module), set()).update(package_of(t) for t in targets)
    return {p: {t for t in ts if t != p} for p, ts in graph.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    state, found = {}, []

    def visit(node, trail):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                found.append(trail[trail.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, [*trail, nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    return found


def test_the_module_graph_has_no_cycle():
    graph = module_graph()
    assert not cycles(graph), "import cycles: " + "; ".join(" -> ".join(c) for c in cycles(graph))
    assert "deepword.inference.runtime" in graph["stages.evaluate.methods"]  # the graph does see imports


def test_the_package_graph_has_no_cycle():
    graph = package_graph()
    assert not cycles(graph), "package cycles: " + "; ".join(" -> ".join(c) for c in cycles(graph))
    assert "deepword" in graph["stages.relation"]


def test_the_engine_and_the_library_import_no_layer_above_them():
    graph = package_graph()
    assert not graph["deepword"] & {"pipeline"} and not any(p.startswith("stages") for p in graph["deepword"])
    assert not any(p.startswith("stages") or p == "deepword" for p in graph["pipeline"])


def test_a_stage_package_imports_no_stage_downstream_of_it():
    """Upstream stages never import downstream ones (conf/config.yaml's DAG): no import runs back up the DAG."""
    stages = OmegaConf.load(REPO / "conf" / "config.yaml").pipeline.stages
    package = {name: package_of(str(s.run).split(":")[0]) for name, s in stages.items()}
    consumers = {name: {c for c, s in stages.items() if name in s.inputs} for name in stages}

    def downstream(name, seen=None):
        seen = set() if seen is None else seen
        for c in consumers[name]:
            if c not in seen:
                seen.add(c)
                downstream(c, seen)
        return seen

    graph = package_graph()
    wrong = []
    for name in stages:
        below = {package[d] for d in downstream(name)} - {package[name]}
        wrong += [f"{package[name]} -> {p}" for p in sorted(graph.get(package[name], set()) & below)]
    assert not wrong, "imports against the DAG: " + ", ".join(wrong)
    assert package["evaluate"] == "stages.evaluate" and "stages.bev" in {package[d] for d in downstream("evaluate")}


def test_inference_never_imports_torch():
    code = ("import sys, stages.cli, stages.inference.infer, stages.inference.tune, deepword.inference.runtime, "
            "deepword.inference.footprints, deepword.scoring.score, deepword.labelling.importer, "
            "deepword.labelling.export, deepword.operating_point.report; "
            "assert 'torch' not in sys.modules, 'torch imported'; "
            "assert not {'lightning', 'hydra'} & set(sys.modules), 'Lightning or Hydra imported'")
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)


def test_the_library_imports_no_lightning_mlflow_or_hydra():
    heavy = ("lightning", "mlflow", "hydra", "omegaconf")
    found = []
    for module, path in modules().items():
        if module.split(".")[0] != "deepword":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            found += [f"{module}: {n}" for n in names if n.split(".")[0] in heavy]
    assert not found, found


def test_the_detector_stage_key_holds_no_relation_code():
    """Training the detector does not depend on the relation network: a change to the relation (or to the
    inference runtime, which imports it) must not invalidate a 15-minute detector training in the cache."""
    from pipeline.codeversion import code_version
    from pipeline.keys import code_packages

    cfg = OmegaConf.load(REPO / "conf" / "config.yaml")
    files = code_version("stages.detector.stage", code_packages(cfg)).files
    assert "stages/detector/stage.py" in files
    assert "deepword/word_format/record.py" in files, "the library's modules are part of a stage's code version"
    assert not [f for f in files if f.startswith(("stages/relation/", "deepword/inference/", "stages/export/",
                                                  "deepword/relation_graph.py"))]
