"""The stage graph declared under ``cfg.pipeline.stages``: parsing, validation, ordering and selection.

Every problem (unknown input, cycle, unknown config key, malformed ``run``) is reported before any
stage runs, naming the stage and the field.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline.checks import parse_checks
from pipeline.errors import PipelineError
from pipeline.outputs import check_declared

STAGE_FIELDS = {"run", "inputs", "optional", "config", "watch", "checks", "dataset", "every_rank", "resolve", "outputs",
                "estimate", "size", "threads"}


@dataclass(frozen=True)
class StageSpec:
    """One DAG node: ``run`` is ``module:function``; ``config`` lists top-level config keys."""

    name: str
    module: str
    function: str
    inputs: tuple[str, ...]
    config: tuple[str, ...]
    watch: tuple[str, ...]
    checks: tuple[tuple[str, tuple[str, ...]], ...] = ()  # (config key, rules): see pipeline.checks
    optional: tuple[str, ...] = ()  # inputs the stage can run without (when pipeline.skip leaves them out)
    dataset: str | None = None  # the output is a dataset of this name: an MLflow dataset input of the run
    # In a launch of several processes (torchrun, srun): every rank calls the stage (it joins a process group,
    # e.g. DDP training), not rank 0 alone; only rank 0's outputs are kept (pipeline.ranks).
    every_rank: bool = False
    # ``module:function`` called at plan time, before any stage runs, to resolve what the declared config only
    # names (pipeline.keys.resolve_extras): e.g. a file to start from, whose content then joins the key.
    resolve: str | None = None
    # ``module:function`` called at plan time for a stage that will run (a miss), never for a hit: its expected
    # seconds on this host (pipeline.estimate); printed and logged, never part of the key
    estimate: str | None = None
    # ``module:function`` called at plan time, before the checks and keys, for every selected stage: a budget sized
    # to this host (e.g. epochs: auto), set in the config as if given on the command line (pipeline.sizing)
    size: str | None = None
    # {name: path relative to the stage's output directory, may hold {field} placeholders}: the files downstream
    # stages read (pipeline.outputs)
    outputs: tuple[tuple[str, str], ...] = ()
    # the config key holding the CPU threads the stage computes on: stages that declare one may run side by side
    # within pipeline.cores (pipeline.schedule); None: the stage runs alone
    threads: str | None = None


def load_hook(stage: str, field: str, target: str):
    """The function a stage's ``field`` (``run`` or a hook) names as ``module:function``, imported now; a clear error
    naming the field when the module has no such function."""
    module, function = target.split(":")
    func = getattr(importlib.import_module(module), function, None)
    if func is None:
        raise PipelineError(f"pipeline.stages.{stage}.{field}: module '{module}' has no '{function}'")
    return func


def _hook(stage: str, node, field: str) -> str | None:
    """A hook field's 'package.module:function' (None when absent)."""
    hook = node.get(field)
    if hook is not None and (not isinstance(hook, str) or hook.count(":") != 1 or not all(hook.split(":"))):
        raise PipelineError(f"pipeline.stages.{stage}.{field}: expected 'package.module:function', got {hook!r}")
    return hook


def _str_list(stage: str, field: str, value) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, ListConfig):
        value = OmegaConf.to_container(value, resolve=True)
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise PipelineError(f"pipeline.stages.{stage}.{field}: expected a list of strings, got {value!r}")
    return tuple(value)


def _parse_stage(name: str, node, cfg: DictConfig) -> StageSpec:
    if not isinstance(node, DictConfig):
        raise PipelineError(f"pipeline.stages.{name}: expected a mapping with run/inputs/config, got {node!r}")
    unknown = set(node.keys()) - STAGE_FIELDS
    if unknown:
        raise PipelineError(f"pipeline.stages.{name}: unknown field(s) {sorted(unknown)}; allowed: {sorted(STAGE_FIELDS)}")
    run = node.get("run")
    if not isinstance(run, str) or run.count(":") != 1 or not all(run.split(":")):
        raise PipelineError(f"pipeline.stages.{name}.run: expected 'package.module:function', got {run!r}")
    module, function = run.split(":")
    resolve, estimate, size = (_hook(name, node, field) for field in ("resolve", "estimate", "size"))
    config = _str_list(name, "config", node.get("config"))
    inputs = _str_list(name, "inputs", node.get("inputs"))
    optional = _str_list(name, "optional", node.get("optional"))
    not_inputs = [o for o in optional if o not in inputs]
    if not_inputs:
        raise PipelineError(f"pipeline.stages.{name}.optional: {not_inputs} not among its inputs {list(inputs)}")
    missing = [k for k in config if k not in cfg]
    if missing:
        raise PipelineError(
            f"pipeline.stages.{name}.config: unknown top-level config key(s) {missing}; "
            f"known keys: {sorted(str(k) for k in cfg.keys())}"
        )
    outputs = node.get("outputs")
    if outputs is None:
        outputs = {}
    elif isinstance(outputs, DictConfig):
        outputs = OmegaConf.to_container(outputs, resolve=True)
    if not isinstance(outputs, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in outputs.items()):
        raise PipelineError(f"pipeline.stages.{name}.outputs: expected a mapping of names to relative paths, got {outputs!r}")
    check_declared(name, outputs)
    threads = node.get("threads")
    if threads is not None and (not isinstance(threads, str) or threads.split(".")[0] not in config
                                or OmegaConf.select(cfg, threads, default=None) is None):
        # under one of its config keys: the threads a stage computes on are part of its cache key
        raise PipelineError(f"pipeline.stages.{name}.threads: expected a key under its config {list(config)} that "
                            f"holds the stage's CPU threads (e.g. relation.train.threads), got {threads!r}")
    every_rank = node.get("every_rank", False)
    if not isinstance(every_rank, bool):
        raise PipelineError(f"pipeline.stages.{name}.every_rank: expected true or false, got {every_rank!r}")
    return StageSpec(
        name=name,
        module=module,
        function=function,
        inputs=inputs,
        config=config,
        watch=_str_list(name, "watch", node.get("watch")),
        checks=parse_checks(name, node.get("checks")),
        optional=optional,
        dataset=None if node.get("dataset") is None else str(node.get("dataset")),
        every_rank=every_rank,
        resolve=resolve,
        estimate=estimate,
        size=size,
        outputs=tuple(outputs.items()),
        threads=threads,
    )


def topological_order(specs: dict[str, StageSpec]) -> list[str]:
    """Stages in dependency order (ties in declaration order); raises on a cycle."""
    order: list[str] = []
    state: dict[str, str] = {}

    def visit(name: str, path: list[str]) -> None:
        if state.get(name) == "done":
            return
        if state.get(name) == "active":
            cycle = path[path.index(name):] + [name]
            raise PipelineError(f"pipeline.stages: dependency cycle {' -> '.join(cycle)}")
        state[name] = "active"
        for dep in specs[name].inputs:
            visit(dep, path + [name])
        state[name] = "done"
        order.append(name)

    for name in specs:
        visit(name, [])
    return order


def load_stages(cfg: DictConfig) -> dict[str, StageSpec]:
    """Parse and validate every declared stage; returns them in topological order."""
    stages_node = OmegaConf.select(cfg, "pipeline.stages")
    if not isinstance(stages_node, DictConfig) or len(stages_node) == 0:
        raise PipelineError("pipeline.stages: no stages declared")
    specs = {str(name): _parse_stage(str(name), stages_node[name], cfg) for name in stages_node}
    for spec in specs.values():
        unknown = [i for i in spec.inputs if i not in specs]
        if unknown:
            raise PipelineError(
                f"pipeline.stages.{spec.name}.inputs: unknown stage(s) {unknown}; declared stages: {list(specs)}"
            )
    return {name: specs[name] for name in topological_order(specs)}


def ancestors(specs: dict[str, StageSpec], name: str) -> set[str]:
    """``name`` and every stage it needs, transitively."""
    needed, todo = set(), [name]
    while todo:
        current = todo.pop()
        if current not in needed:
            needed.add(current)
            todo.extend(specs[current].inputs)
    return needed


def check_stage_names(specs: dict[str, StageSpec], names: list[str], field: str) -> None:
    unknown = [n for n in names if n not in specs]
    if unknown:
        raise PipelineError(f"{field}: unknown stage(s) {unknown}; declared stages: {list(specs)}")


def select_stages(specs: dict[str, StageSpec], until: str | None,
                  skip: list[str] | tuple[str, ...] = ()) -> tuple[list[str], dict[str, str]]:
    """(stages to run in order, {stage left out: why}): all of them, or ``until`` and its ancestors; minus
    the ``skip`` stages and every stage with a skipped stage among its required (not ``optional``) inputs."""
    check_stage_names(specs, list(skip), "pipeline.skip")
    if until is not None:
        check_stage_names(specs, [until], "pipeline.until")
        if until in skip:
            raise PipelineError(f"pipeline.until={until} is also in pipeline.skip: nothing would be left to run")
    needed = set(specs) if until is None else ancestors(specs, until)
    why: dict[str, str] = {n: "not needed for pipeline.until" for n in specs if n not in needed}
    why.update({n: "pipeline.skip" for n in skip})
    for name, spec in specs.items():  # topological order: an input's fate is known before its consumers'
        if name in why:
            continue
        lost = [i for i in spec.inputs if i in why and i not in spec.optional]
        if lost:
            why[name] = f"needs {', '.join(lost)}"
    if until is not None and until in why:
        raise PipelineError(f"pipeline.until={until}: it {why[until]}, which pipeline.skip leaves out")
    return [n for n in specs if n not in why], why
