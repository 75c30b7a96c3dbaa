"""``run_pipeline(cfg)``: validate, plan, run the missing stages, record everything in MLflow.

Order matters for speed and safety: everything that can fail on configuration (stage graph, force/until
names, config keys, server reachability) is checked before any stage runs, and hits are decided from
key parts alone, before any stage module is imported.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from pipeline import tracking
from pipeline.cache import IMPORTS_MEMO, VERIFY_MODES, Cache, Entry, now_iso
from pipeline.checks import check_values
from pipeline.codeversion import persistent_imports
from pipeline.dag import StageSpec, check_stage_names, load_hook, load_stages, select_stages
from pipeline.errors import PipelineError
from pipeline.estimate import estimate_params, estimate_stage, format_estimates, time_budget
from pipeline.keys import KeyParts, PlanContext, file_digest, key_parts
from pipeline.outputs import StageInputs, missing_outputs
from pipeline.plan import StagePlan, explain_hit, explain_miss, format_plan
from pipeline.ranks import LAUNCH_ID_VARIABLE, POLL_SECONDS, LaunchFile, Rank, current_rank, read_launch_file
from pipeline.report import summary_table, write_summary
from pipeline.run_record import DIGEST_TAG, UNKNOWN, RecordedRun, find_in_sqlite, run_digest
from pipeline.schedule import cores, stage_threads, waves
from pipeline.sizing import apply_sized, format_sized, size_stages, sized_params, sized_values
from pipeline.stage_call import Job, Outcome, StageProcessDied, call_stage, run_side_by_side, stage_cfg
from pipeline.tracker import check_server, flatten_params, open_tracker


def _say(message: str) -> None:
    print(message, flush=True)


def _hydra_runtime() -> tuple[Path | None, Path | None, list[str]]:
    """(launch dir, run output dir, task overrides) when running under Hydra, else (None, None, [])."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None, None, []
    hc = HydraConfig.get()
    return Path(hc.runtime.cwd), Path(hc.runtime.output_dir), list(hc.overrides.task)


def _git_commit(where: Path) -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=5, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "unknown"


def _settings(cfg: DictConfig, launch_dir: Path) -> dict:
    p = cfg.pipeline
    force = list(p.get("force") or [])
    until = p.get("until")
    skip = list(p.get("skip") or [])
    verify = p.get("verify", "fast")
    if verify not in VERIFY_MODES:
        raise PipelineError(f"pipeline.verify: expected one of {VERIFY_MODES}, got {verify!r}")
    cache_dir = Path(str(p.cache_dir)).expanduser()
    if not cache_dir.is_absolute():
        cache_dir = launch_dir / cache_dir
    t = cfg.get("tracking")
    if t is None:
        raise PipelineError("config has no 'tracking' group (tracking.uri, tracking.experiment)")
    return {
        "force": force, "until": until, "skip": skip, "verify": verify, "cache_dir": cache_dir,
        "uri": str(t.uri), "experiment": str(t.get("experiment", "deepword")),
        "require_server": bool(t.get("require_server", False)),
    }


def _context(settings: dict) -> PlanContext:
    return PlanContext(settings["cache_dir"], settings["uri"])


def _plan(specs: dict[str, StageSpec], selected: list[str], cfg: DictConfig, cache: Cache,
          force: list[str], verify: str, context: PlanContext) -> list[StagePlan]:
    keys: dict[str, str] = {}
    parts: dict[str, KeyParts] = {}
    with persistent_imports(cache.root / IMPORTS_MEMO):  # each source file read once, parsed once per content
        for name in selected:
            try:
                parts[name] = key_parts(specs[name], cfg, keys, context)
            except OmegaConfBaseException as exc:
                raise PipelineError(f"stage '{name}': cannot resolve its config {list(specs[name].config)}: "
                                    f"{exc}") from exc
            keys[name] = parts[name].key
    plans = []
    for name in selected:
        latest = cache.read_latest(name)
        if name in force:
            plans.append(StagePlan(name, parts[name], hit=False, reason="forced (pipeline.force)", forced=True))
            continue
        entry, problem = cache.lookup(name, parts[name].key, verify)
        if entry is not None:
            plans.append(StagePlan(name, parts[name], hit=True, reason=explain_hit(parts[name], latest), entry=entry))
        else:
            plans.append(StagePlan(name, parts[name], hit=False, reason=explain_miss(parts[name], latest, problem)))
    return plans


def _stage_inputs(spec: StageSpec, parts: KeyParts, outputs: dict[str, Path],
                  specs: dict[str, StageSpec]) -> StageInputs:
    """The upstream outputs (an optional input may be left out) with their declared outputs, and the files the
    resolve hook named, whose content must still be what the key holds."""
    inputs = StageInputs(spec.name, {i: outputs[i] for i in spec.inputs if i in outputs}, spec.inputs,
                         {i: dict(specs[i].outputs) for i in spec.inputs})
    for name, path in parts.files.items():
        if not Path(path).is_file() or file_digest(path) != parts.inputs[name]:
            raise PipelineError(f"stage '{spec.name}': {name} file {path} changed or vanished since the plan; "
                                "run again")
        inputs[name] = Path(path)
    return inputs


def _check_outputs(spec: StageSpec, out_dir: Path, what: str) -> None:
    missing = missing_outputs(out_dir, dict(spec.outputs))
    if missing:
        hint = "" if what == "did not write" else f"; recompute it with pipeline.force=[{spec.name}]"
        raise PipelineError(f"stage '{spec.name}' {what} its declared output(s) {missing} in {out_dir}{hint}")


def _begin(plan: StagePlan, spec: StageSpec, cache: Cache, launch: LaunchFile) -> Path:
    """The stage's work dir (resumed where an interrupted attempt left one); the caller holds the key's lock."""
    if spec.every_rank and launch.rank.world_size > 1 and cache.partial_dir(spec.name, plan.key).exists():
        # The other ranks start the stage from nothing, and ranks of one process group must start alike.
        _say(f"Stage '{spec.name}': not resuming an interrupted attempt: {launch.rank.world_size} ranks start it afresh")
        cache.abort(cache.partial_dir(spec.name, plan.key))
    tmp, resumed = cache.begin(spec.name, plan.key)
    if resumed:
        _say(f"Stage '{spec.name}': resuming from what an interrupted attempt left in {tmp}")
    if spec.every_rank:
        launch.computing(spec.name, plan.key, resumed, tmp / "out")
    return tmp


def _commit(plan: StagePlan, spec: StageSpec, cache: Cache, tmp: Path, metrics: dict[str, float], seconds: float,
            run_id: str) -> Entry:
    _check_outputs(spec, tmp / "out", "did not write")
    manifest = {
        "stage": spec.name, "parts": plan.parts.to_json(), "metrics": metrics, "seconds": seconds,
        "mlflow_run_id": run_id, "created": now_iso(),
    }
    return cache.commit(spec.name, plan.key, tmp, manifest)


def _failed(spec: StageSpec, cache: Cache, tmp: Path, exc: BaseException) -> None:
    """A failure, not an interruption, leaves nothing to resume: the next attempt starts clean. An interruption
    (KeyboardInterrupt / SystemExit on SIGTERM, a stage's process killed) keeps the work dir, and a re-run resumes
    from it."""
    if isinstance(exc, Exception) and not isinstance(exc, StageProcessDied):
        cache.abort(tmp)
        if not isinstance(exc, PipelineError):
            exc.pipeline_stage = spec.name  # the CLI reports it as this stage's failure, in one line


def _compute(plan: StagePlan, spec: StageSpec, cache: Cache, inputs: dict[str, Path], run_id: str, uri: str,
             launch: LaunchFile) -> Entry:
    """Run the stage into its work dir and commit it; the caller holds the key's lock."""
    tmp = _begin(plan, spec, cache, launch)
    start = time.perf_counter()
    try:
        metrics = call_stage(spec, plan.parts, inputs, tmp / "out", (uri, run_id))
        return _commit(plan, spec, cache, tmp, metrics, time.perf_counter() - start, run_id)
    except BaseException as exc:
        _failed(spec, cache, tmp, exc)
        raise


def _announce_hit(plan: StagePlan, spec: StageSpec) -> None:
    # an entry computed before the stage declared an output must not reach a stage that reads it
    _check_outputs(spec, plan.entry.out_dir, "has a cache entry without")
    _say(f"Stage '{plan.name}' didn't change, skipping" if plan.reason == "didn't change"
         else f"Stage '{plan.name}': {plan.reason}, using it")


def _remember_latest(cache: Cache, plan: StagePlan) -> None:
    if cache.read_latest(plan.name) != plan.parts.to_json():
        cache.write_latest(plan.name, plan.parts.to_json())


def _stage_result(plan: StagePlan, entry: Entry, seconds: float, run_id: str) -> dict:
    return {
        "key": plan.key, "hit": plan.hit, "reason": plan.reason, "seconds": seconds,
        "output_dir": str(entry.out_dir), "metrics": dict(entry.manifest.get("metrics", {})), "mlflow_run_id": run_id,
        "computed_by_run": entry.manifest.get("mlflow_run_id", ""),
    }


def _lock(cache: Cache, plan: StagePlan):
    return cache.lock(plan.name, plan.key,
                      on_wait=lambda: _say(f"Stage '{plan.name}': waiting for another pipeline computing it"))


def _still_missing(plan: StagePlan, cache: Cache, verify: str) -> bool:
    """Under the key's lock: False when a concurrent pipeline computed the entry meanwhile (the plan becomes a hit);
    a forced stage is computed again."""
    if not plan.forced:
        entry, _ = cache.lookup(plan.name, plan.key, verify)
        if entry is not None:
            plan.hit, plan.reason, plan.entry = True, "computed meanwhile by a concurrent pipeline", entry
            return False
    return True


def _open_run(plan: StagePlan, spec: StageSpec, tracker, parent_id: str, outputs: dict[str, Path], settings: dict,
              specs: dict[str, StageSpec], beside: list[str] = ()) -> tuple[StageInputs, str]:
    """Announce the stage, gather its inputs and open its MLflow child run: (inputs, run id)."""
    also = f"; beside {', '.join(repr(b) for b in beside)}" if beside else ""
    _say(f"Running stage '{plan.name}' ({plan.reason}{also})")
    inputs = _stage_inputs(spec, plan.parts, outputs, specs)
    run_id = tracker.create_run(
        plan.name, {"cache": "miss", "cache_key": plan.key, "stage": plan.name, **settings["run_tags"],
                    **plan.parts.tags}, parent_id
    )
    return inputs, run_id


def _run_stage(plan: StagePlan, spec: StageSpec, cache: Cache, tracker, parent_id: str,
               outputs: dict[str, Path], settings: dict, launch: LaunchFile, specs: dict[str, StageSpec]) -> dict:
    """One stage in this process: a hit is recorded, a miss computed (under its key's lock) and recorded."""
    start = time.perf_counter()
    if not plan.hit:
        with _lock(cache, plan):
            if _still_missing(plan, cache, settings["verify"]):
                inputs, run_id = _open_run(plan, spec, tracker, parent_id, outputs, settings, specs)
                try:
                    plan.entry = _compute(plan, spec, cache, inputs, run_id, settings["uri"], launch)
                except BaseException:
                    tracker.end(run_id, "FAILED")
                    raise
    return _record(plan, spec, cache, tracker, parent_id, settings, time.perf_counter() - start)


def _run_side_by_side(wave: list[StagePlan], specs: dict[str, StageSpec], cache: Cache, tracker, parent_id: str,
                      outputs: dict[str, Path], settings: dict, launch: LaunchFile) -> dict[str, dict]:
    """The wave's stages at once (``pipeline.schedule``): an ``every_rank`` stage in this process, each other one in
    a process of its own; their locks, work dirs, commits and MLflow runs stay in this process. A stage that fails does not stop the others: their entries are
    committed and recorded, then the first failure is raised."""
    results: dict[str, dict] = {}
    errors: list[BaseException] = []
    with ExitStack() as locks:
        for plan in wave:
            locks.enter_context(_lock(cache, plan))
        missing = [p for p in wave if _still_missing(p, cache, settings["verify"])]
        jobs, runs, work = {}, {}, {}
        for plan in missing:
            spec = specs[plan.name]
            inputs, runs[plan.name] = _open_run(plan, spec, tracker, parent_id, outputs, settings, specs,
                                                [p.name for p in missing if p is not plan])
            work[plan.name] = _begin(plan, spec, cache, launch)
            jobs[plan.name] = Job(spec, plan.parts, inputs, work[plan.name] / "out", (settings["uri"], runs[plan.name]))

        def answered(name: str, outcome: Outcome, running: list[str]) -> None:
            still = f"; {', '.join(repr(r) for r in running)} still running" if running else ""
            verb = "done" if outcome.error is None else "failed"
            _say(f"Stage '{name}' {verb} in {outcome.seconds:.1f} s{still}")

        try:
            here = next((n for n in jobs if specs[n].every_rank), None)  # its ranks follow this process
            outcomes = run_side_by_side(jobs, answered, here) if jobs else {}
        except BaseException:  # interrupted: the work dirs stay for a re-run to resume from
            for run_id in runs.values():
                tracker.end(run_id, "FAILED")
            raise
        for plan in missing:
            spec, outcome, tmp = specs[plan.name], outcomes[plan.name], work[plan.name]
            try:
                if outcome.error is not None:
                    raise outcome.error
                plan.entry = _commit(plan, spec, cache, tmp, outcome.metrics, outcome.seconds, runs[plan.name])
            except BaseException as exc:
                _failed(spec, cache, tmp, exc)
                if outcome.traceback:
                    exc.stage_traceback = outcome.traceback  # where it failed, in the stage's process
                tracker.end(runs[plan.name], "FAILED")
                errors.append(exc)
    for plan in wave:
        if plan.entry is not None:
            seconds = outcomes[plan.name].seconds if plan.name in outcomes else 0.0
            results[plan.name] = _record(plan, specs[plan.name], cache, tracker, parent_id, settings, seconds,
                                         announce_done=False)
    if errors:
        raise errors[0]
    return results


def _record(plan: StagePlan, spec: StageSpec, cache: Cache, tracker, parent_id: str, settings: dict,
            seconds: float, announce_done: bool = True) -> dict:
    """Log the stage's run (a hit gets a run of its own naming the run that computed it) and its result."""
    name, key, entry = plan.name, plan.key, plan.entry
    if plan.hit:
        _announce_hit(plan, spec)
    metrics = dict(entry.manifest.get("metrics", {}))
    computed_by = entry.manifest.get("mlflow_run_id", "")
    if plan.hit:
        run_id = tracker.create_run(
            name, {"cache": "hit", "cache_key": key, "stage": name, "computed_by_run": computed_by,
                   **settings["run_tags"], **plan.parts.tags}, parent_id
        )
    else:
        run_id = computed_by
        tracker.log_artifacts(run_id, str(entry.out_dir / "artifacts"))
        if announce_done:
            _say(f"Stage '{name}' done in {seconds:.1f} s")
    tracker.log(run_id, metrics={**metrics, f"{name}.seconds": seconds},
                tags={"computed_by_run": computed_by, "computed_seconds": f"{entry.manifest.get('seconds', 0):.3f}"})
    tracker.end(run_id, "FINISHED")
    if spec.dataset is not None:  # the parent run's Dataset column: this output, identified by its cache key
        tracker.log_dataset(parent_id, spec.dataset, key, str(entry.out_dir.resolve()))
    _remember_latest(cache, plan)
    return _stage_result(plan, entry, seconds, run_id)


def _hydra_choices() -> dict[str, str]:
    """The config group options this run composed (``relation/backbone`` -> ``conv_fc``), Hydra's own left out."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return {}
    choices = HydraConfig.get().runtime.choices
    return {str(g): str(o) for g, o in choices.items() if o is not None and not str(g).startswith("hydra")}


def _run_name(cfg: DictConfig, overrides: list[str], choices: dict[str, str]) -> str:
    """Profile, the options of ``pipeline.run_name_groups`` (what tells runs apart in the UI), then the
    remaining command-line overrides."""
    groups = [g for g in (cfg.pipeline.get("run_name_groups") or []) if g in choices]
    named = [f"{g}={choices[g]}" for g in groups]
    # Where the run is stored and cached does not change its results: left out of the name (kept as a tag).
    shown = [o for o in overrides if not o.startswith(("profile=", "pipeline.cache_dir=", "tracking.", "hydra."))
             and o not in named]
    return " ".join([str(cfg.get("profile_name", "pipeline")), *named, *shown])


def run_pipeline(cfg: DictConfig, run_dir: Path | None = None, in_process_tracking: bool | None = None) -> dict:
    """Run the DAG declared in ``cfg.pipeline.stages``; returns the summary (also in ``summary.json``).

    ``run_dir`` defaults to Hydra's run output directory (the launch directory outside Hydra).
    ``in_process_tracking``: None picks in-process MLflow when it is already imported, else the worker.
    """
    t0 = time.perf_counter()
    rank = current_rank()
    launch_dir, hydra_dir, overrides = _hydra_runtime()
    launch_dir = launch_dir or Path(os.getcwd())
    run_dir = run_dir or hydra_dir or launch_dir
    settings = _settings(cfg, launch_dir)
    if not rank.is_zero:
        return _follow_rank_zero(rank, cfg, settings)
    launch = LaunchFile(settings["cache_dir"], rank)
    # Processes a stage starts (Lightning's ddp launcher re-runs this command) learn which launch they join.
    previous_id = os.environ.get(LAUNCH_ID_VARIABLE)
    os.environ[LAUNCH_ID_VARIABLE] = launch.launch_id
    try:
        summary = _run_rank_zero(cfg, rank, settings, launch, run_dir, launch_dir, overrides, in_process_tracking, t0)
    except BaseException as exc:
        launch.failed(exc)
        raise
    finally:
        if previous_id is None:
            os.environ.pop(LAUNCH_ID_VARIABLE, None)
        else:
            os.environ[LAUNCH_ID_VARIABLE] = previous_id
    launch.finished()
    return summary


def _split_checks(spec: StageSpec, cfg: DictConfig) -> tuple[tuple, tuple]:
    """The stage's checks to make before sizing, and those on a key a stage with a size hook leaves as a word
    (``auto``) for its hook, made once it is sized."""
    if spec.size is None:
        return spec.checks, ()
    later = tuple((key, rules) for key, rules in spec.checks
                  if isinstance(OmegaConf.select(cfg, key, default=None), str))
    return tuple(c for c in spec.checks if c not in later), later


def _run_rank_zero(cfg, rank: Rank, settings, launch: LaunchFile, run_dir, launch_dir, overrides,
                   in_process_tracking, t0) -> dict:
    specs = load_stages(cfg)
    check_stage_names(specs, settings["force"], "pipeline.force")
    selected, left_out = select_stages(specs, settings["until"], settings["skip"])
    # Checked before the size hooks: a probe takes seconds and writes the memo, and a bad value elsewhere must stop
    # the run first. A checked key that a sized stage leaves as a word (``auto``) is the hook's to fill: checked after.
    after_sizing = {}
    for name in selected:
        now, after_sizing[name] = _split_checks(specs[name], cfg)
        check_values(cfg, name, now)
    if settings["require_server"]:
        check_server(settings["uri"])
    cfg, sized = size_stages(specs, selected, cfg, settings["cache_dir"], _context(settings))
    if sized:
        _say(format_sized(sized, settings["cache_dir"]))
    for name, checks in after_sizing.items():
        check_values(cfg, name, checks)
    if in_process_tracking is None:  # decided now: a resolve hook may import MLflow while planning
        in_process_tracking = "mlflow" in sys.modules
    budget = time_budget(cfg)
    cache = Cache(settings["cache_dir"])
    plans = _plan(specs, selected, cfg, cache, settings["force"], settings["verify"], _context(settings))
    _say(format_plan(plans, str(cache.root), left_out))
    grouped = _waves(plans, specs, cfg, launch)  # before anything runs: a bad threads value stops the run here
    # only the stages that will run: a hit never calls its hook (an all-hit re-run imports no stage code)
    # pipeline.estimate: false skips the hooks (a probe costs seconds: the smoke profile's tests run hundreds of plans)
    estimating = bool(OmegaConf.select(cfg, "pipeline.estimate", default=True))
    estimates = [e for p in plans if not p.hit and estimating
                 if (e := estimate_stage(specs[p.name], cfg, _context(settings))) is not None]
    if estimates:
        _say(format_estimates(estimates, budget, str(cfg.get("profile_name", "")), grouped))
    launch.start({p.name: p.key for p in plans}, sized_values(sized))
    if rank.world_size > 1:
        _say(f"{rank.described} (launch {launch.launch_id}): this rank plans, tracks and writes the cache")
    ignored = [n for n in settings["force"] if n in left_out]
    if ignored:
        _say(f"note: forced stage(s) {ignored} are left out of this run ({'; '.join(left_out[n] for n in ignored)}); "
             "not run")
    for name in selected:
        cache.sweep(name)

    record = _parent_record(cfg, plans, settings, launch_dir, overrides, left_out)
    recorded, tracker = None, None
    if all(p.hit for p in plans):  # nothing to compute: is this exact run already in MLflow?
        recorded = find_in_sqlite(settings["uri"], settings["experiment"], record["digest"])
        if recorded == UNKNOWN:  # not a store the engine reads itself: MLflow answers
            tracker = open_tracker(settings["uri"], settings["experiment"], in_process_tracking)
            recorded = _ask_tracker(tracker, record["digest"])
    if recorded is not None:
        if tracker is not None:
            tracker.close()
        return _use_recorded(recorded, specs, plans, cache, settings, run_dir, left_out, t0)
    tracker = tracker or open_tracker(settings["uri"], settings["experiment"], in_process_tracking)
    try:
        return _run_all(cfg, specs, plans, cache, tracker, settings, run_dir, record, left_out, t0, launch, grouped,
                        estimates, sized)
    finally:
        tracker.close()


def _ask_tracker(tracker, digest: str) -> RecordedRun | None:
    try:
        return RecordedRun.from_json(tracker.find_recorded(digest))
    except BaseException:
        tracker.close()
        raise


def _parent_record(cfg, plans, settings, launch_dir, overrides, left_out) -> dict:
    """The parent run's name, tags and params, and the digest that identifies them (``pipeline.run_record``)."""
    resolved = OmegaConf.to_container(cfg, resolve=True)
    tags = {
        "profile": str(cfg.get("profile_name", "")),
        "seed": str(cfg.get("seed", "")),
        "git_commit": _git_commit(launch_dir),
        "overrides": " ".join(overrides),
    }
    choices = _hydra_choices()
    tags.update({f"choice.{g}": o for g, o in choices.items()})
    for plan in plans:  # the stages' resolve hooks' tags (e.g. what a stage started from) describe the run too
        tags.update(plan.parts.tags)
    name = _run_name(cfg, overrides, choices)
    params = flatten_params(resolved)
    digest = run_digest(settings["experiment"], name, tags, params, {p.name: p.key for p in plans}, left_out)
    return {"name": name, "tags": tags, "params": params, "digest": digest}


def _use_recorded(recorded: RecordedRun, specs, plans, cache: Cache, settings, run_dir, left_out, t0) -> dict:
    """Every stage is a hit and this exact run is already recorded: name that run, log nothing."""
    results: dict[str, dict] = {}
    for plan in plans:
        start = time.perf_counter()
        _announce_hit(plan, specs[plan.name])
        _remember_latest(cache, plan)
        results[plan.name] = _stage_result(plan, plan.entry, time.perf_counter() - start,
                                           recorded.children.get(plan.name, ""))
    summary = {
        "pipeline_seconds": time.perf_counter() - t0,
        "up_to_date": True,
        "mlflow_run_id": recorded.run_id,
        "already_recorded": True,
        "tracking_uri": settings["uri"],
        "experiment": settings["experiment"],
        "cache_dir": str(cache.root),
        "stages": results,
        "not_run": left_out,
    }
    write_summary(run_dir, summary)
    _say(summary_table(summary))
    started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(recorded.start_time / 1000))
    _say(f"Already recorded: MLflow run {recorded.run_id} ('{recorded.name}', started {started}) has the same "
         "cache keys, config, tags and commit; nothing new logged.")
    _say("Pipeline up to date.")
    return summary


def _waves(plans: list[StagePlan], specs: dict[str, StageSpec], cfg: DictConfig, launch: LaunchFile) -> list[list[str]]:
    """The misses grouped into the waves that run one after the other (``pipeline.schedule``). A launch of several
    ranks runs one stage at a time: its other ranks follow rank 0 stage by stage."""
    misses = [p for p in plans if not p.hit]
    if launch.rank.world_size > 1:
        return [[p.name] for p in misses]
    threads = {p.name: stage_threads(p.name, specs[p.name].threads, cfg) for p in misses}
    return waves([p.name for p in misses], {p.name: specs[p.name].inputs for p in misses}, threads, cores(cfg),
                 {p.name for p in misses if specs[p.name].every_rank})


def _steps(plans: list[StagePlan], grouped: list[list[str]]) -> list[list[StagePlan]]:
    """The plans in the order they run: each hit alone (it computes nothing), the misses in the waves of
    ``pipeline.schedule``, each wave after the hits planned before its last stage."""
    by_name = {p.name: p for p in plans}
    position = {p.name: i for i, p in enumerate(plans)}
    steps, next_hit = [], 0
    for wave in grouped:
        last = max(position[n] for n in wave)
        for plan in plans[next_hit:last + 1]:
            if plan.hit:
                steps.append([plan])
        next_hit = max(next_hit, last + 1)
        steps.append([by_name[n] for n in wave])
    steps.extend([p] for p in plans[next_hit:] if p.hit)
    return steps


def _run_all(cfg, specs, plans, cache, tracker, settings, run_dir, record, left_out, t0,
             launch: LaunchFile, grouped: list[list[str]], estimates=(), sized=()) -> dict:
    parent_tags = {**record["tags"], DIGEST_TAG: record["digest"]}
    # Every stage child run carries them too: a child row alone says which seed and code made it.
    settings["run_tags"] = {k: parent_tags[k] for k in ("profile", "seed", "git_commit")}
    parent_id = tracker.create_run(record["name"], parent_tags)
    # the forecast beside the record, outside its digest: compare estimate.<stage>.seconds with <stage>.seconds
    tracker.log(parent_id, params={**record["params"], **estimate_params(list(estimates)), **sized_params(list(sized))})
    results: dict[str, dict] = {}
    outputs: dict[str, Path] = {}
    try:
        for step in _steps(plans, grouped):
            if len(step) == 1:
                results[step[0].name] = _run_stage(step[0], specs[step[0].name], cache, tracker, parent_id, outputs,
                                                   settings, launch, specs)
            else:
                results.update(_run_side_by_side(step, specs, cache, tracker, parent_id, outputs, settings, launch))
            for plan in step:
                outputs[plan.name] = Path(results[plan.name]["output_dir"])
    except BaseException:
        tracker.end(parent_id, "FAILED")
        raise
    results = {p.name: results[p.name] for p in plans}  # the plan's order, whatever ran beside what
    total = time.perf_counter() - t0
    parent_metrics = {"pipeline.seconds": total}
    for name, r in results.items():
        parent_metrics.update(r["metrics"])
        parent_metrics[f"{name}.seconds"] = r["seconds"]
    tracker.log(parent_id, metrics=parent_metrics)
    tracker.end(parent_id, "FINISHED")
    tracker.flush()  # the record is complete (or its error raised) before the summary says so
    summary = {
        "pipeline_seconds": total,
        "up_to_date": all(r["hit"] for r in results.values()),
        "mlflow_run_id": parent_id,
        "already_recorded": False,
        "tracking_uri": settings["uri"],
        "experiment": settings["experiment"],
        "cache_dir": str(cache.root),
        "stages": results,
        "not_run": left_out,  # stage -> why it was left out
        "estimates": {e.stage: e.seconds for e in estimates},  # plan-time forecasts (pipeline.estimate)
        "sized": sized_values(list(sized)),  # budgets sized to this host (pipeline.sizing)
    }
    write_summary(run_dir, summary)
    _say(summary_table(summary))
    if summary["up_to_date"]:
        _say("Pipeline up to date.")
    return summary



# -- ranks other than 0 (pipeline.ranks) ---------------------------------------------------------------


class _RankZeroWatch:
    """What a waiting rank checks on every poll: rank 0's launch file (its error, its plan) and whether the
    process that started this rank still runs (a parent that died leaves no one to wait for)."""

    def __init__(self, rank: Rank, cache: Cache, my_plan: dict[str, str] | None = None):
        self.rank, self.cache, self.my_plan = rank, cache, my_plan  # None: this rank has no plan yet to compare
        self.parent = os.getppid()

    def read(self) -> dict:
        state = read_launch_file(self.cache.root, self.rank.launch_id) or {}
        if state.get("error"):
            raise PipelineError(f"{self.rank.described}: rank 0 of launch {self.rank.launch_id} failed "
                                f"({state['error']}); this rank stops too")
        theirs, mine = state.get("plan") or {}, self.my_plan
        differ = [] if not theirs or mine is None else sorted(
            s for s in set(theirs) | set(mine) if theirs.get(s) != mine.get(s))
        if differ:
            raise PipelineError(
                f"{self.rank.described}: rank 0 planned other cache keys for stage(s) {differ}: the ranks run "
                "different code or config (check every node has the same checkout and command line)")
        if os.getppid() != self.parent:
            raise PipelineError(f"{self.rank.described}: the process that launched this rank exited")
        return state


def _rank_zero_plan(watch: _RankZeroWatch) -> dict:
    """Rank 0's launch file once it holds its plan (``watch.read`` raises on its error)."""
    while not (state := watch.read()).get("plan"):
        time.sleep(POLL_SECONDS)
    return state


def _entry_if_complete(cache: Cache, stage: str, key: str, verify: str) -> Entry | None:
    if not (cache.entry_dir(stage, key) / "manifest.json").is_file():  # cheap test first: this runs per poll
        return None
    return cache.lookup(stage, key, verify)[0]


def _follow_rank_zero(rank: Rank, cfg: DictConfig, settings: dict) -> dict:
    """Build rank 0's plan, then for each ``every_rank`` stage in order: join it when rank 0 computes it
    (the stage runs in a scratch directory, deleted afterwards), skip it when rank 0 uses its cache entry.
    Writes nothing to the cache or MLflow."""
    if rank.launch_id is None:
        raise PipelineError(f"{rank.described}: cannot tell which launch this rank belongs to; set "
                            f"{LAUNCH_ID_VARIABLE} to one value on every rank (torchrun and SLURM provide one)")
    specs = load_stages(cfg)
    selected, _ = select_stages(specs, settings["until"], settings["skip"])
    cache = Cache(settings["cache_dir"])
    watch = _RankZeroWatch(rank, cache)
    if any(specs[n].size for n in selected):  # rank 0's sizing, not this rank's own probe
        cfg = apply_sized(cfg, _rank_zero_plan(watch).get("sized") or {})
    verify = settings["verify"]
    forced = set(settings["force"])
    keys: dict[str, str] = {}
    parts: dict[str, KeyParts] = {}
    for name in selected:
        parts[name] = key_parts(specs[name], cfg, keys, _context(settings))
        keys[name] = parts[name].key
    watch.my_plan = keys
    _say(f"{rank.described} (launch {rank.launch_id}): following rank 0, which alone writes the cache and MLflow")
    joined, skipped = [], []
    for name in (n for n in selected if specs[n].every_rank):
        key = keys[name]
        while True:
            # The entry first, the announcement second: an entry rank 0 committed in this launch is still
            # announced then. A forced stage is computed again although its entry exists: only announced.
            in_cache = name not in forced and _entry_if_complete(cache, name, key, verify) is not None
            state = watch.read()
            computing = (state.get("computing") or {}).get(name)
            if computing is not None:
                if computing["key"] != key:
                    raise PipelineError(f"{rank.described}: rank 0 computes stage '{name}' under another key: the "
                                        "ranks run different code or config")
                break
            if in_cache:
                break
            time.sleep(POLL_SECONDS)
        if computing is None:
            _say(f"{rank.described}: stage '{name}' is in the cache, nothing to join")
            skipped.append(name)
            continue
        inputs = _stage_inputs(specs[name], parts[name], {}, specs)
        for i in specs[name].inputs:
            if i not in keys:
                continue  # an optional input left out of this run
            # Committed before rank 0 started this stage; a network filesystem may show it a little later.
            while (entry := _entry_if_complete(cache, i, keys[i], verify)) is None:
                watch.read()
                time.sleep(POLL_SECONDS)
            inputs[i] = entry.out_dir
        _say(f"{rank.described}: joining stage '{name}' (rank 0 computes it)")
        _join_stage(specs[name], parts[name], inputs, computing, rank)
        joined.append(name)
    _say(f"{rank.described}: done (joined {joined or 'no stage'}); rank 0 records the results")
    return {"rank": rank.index, "world_size": rank.world_size, "launch_id": rank.launch_id,
            "joined": joined, "skipped": skipped}


def _join_stage(spec: StageSpec, parts: KeyParts, inputs: dict[str, Path], computing: dict, rank: Rank) -> None:
    scratch = Path(tempfile.mkdtemp(prefix=f"pipeline-{spec.name}-rank{rank.index}-"))
    try:
        out = scratch / "out"
        if computing.get("resumed"):
            # Rank 0 resumes from its work dir (e.g. a last checkpoint): start from the same state. Rank 0
            # started this rank from inside the stage and waits for it, so the directory is not changing.
            shutil.copytree(computing["work_dir"], out)
        else:
            out.mkdir()
        func = load_hook(spec.name, "run", f"{spec.module}:{spec.function}")
        tracking.set_active(None)  # only rank 0 logs
        func(stage_cfg(parts), inputs, out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
