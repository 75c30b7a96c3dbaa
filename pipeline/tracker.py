"""The engine's side of MLflow: a server reachability check, config flattening for params, and two
interchangeable trackers: in-process (``MlflowOps`` directly) and the worker process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from pipeline.errors import PipelineError
from pipeline.mlflow_ops import MlflowOps

MAX_PARAM_CHARS = 500  # MLflow's classic limit on a param value; longer values are truncated
MAX_KEY_CHARS = 250


def check_server(uri: str, timeout: float = 3.0) -> None:
    """Fail fast when a required tracking server cannot be reached (before any stage runs)."""
    if not uri.startswith(("http://", "https://")):
        raise PipelineError(
            f"tracking.require_server is true but tracking.uri={uri!r} is not an http(s) server URI"
        )
    import urllib.error  # lazily: the CLI imports this module before it starts the tracking worker
    import urllib.request

    url = uri.rstrip("/") + "/health"
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            if response.status != 200:
                raise PipelineError(f"MLflow server at {uri} answered {response.status} on /health")
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise PipelineError(
            f"MLflow tracking server {uri} is not reachable ({reason}); no stage was run. "
            "Start it (`make ui` serves ./mlflow.db on 127.0.0.1:5000), set MLFLOW_TRACKING_URI, "
            "or use tracking=local."
        ) from exc


def flatten_params(value, prefix: str = "") -> dict[str, str]:
    """Dotted keys -> string values (lists as JSON), truncated to MLflow's limits."""
    out: dict[str, str] = {}
    if isinstance(value, dict):
        for k, v in value.items():
            out.update(flatten_params(v, f"{prefix}{k}."))
        return out
    key = prefix[:-1][:MAX_KEY_CHARS]
    text = value if isinstance(value, str) else json.dumps(value)
    if len(text) > MAX_PARAM_CHARS:
        text = text[: MAX_PARAM_CHARS - 14] + "...[truncated]"
    out[key] = text
    return out


class InProcessTracker:
    """MLflow calls in this process (cheap when MLflow is already imported, e.g. under pytest)."""

    def __init__(self, uri: str, experiment: str):
        try:
            self._ops = MlflowOps(uri, experiment)
        except Exception as exc:
            raise PipelineError(f"cannot open MLflow tracking store {uri!r}: {exc}") from exc

    def __getattr__(self, op):
        return getattr(self._ops, op)

    def flush(self) -> None:
        pass  # every call has already completed

    def close(self) -> None:
        pass


class WorkerTracker:
    """MLflow calls forwarded to ``python -m pipeline.mlflow_worker`` (see that module for why).

    Only ``create_run`` waits for its answer (the engine needs the run id); ``init``, ``log``, ``end``,
    ``log_dataset`` and ``log_artifacts`` are posted without waiting, so the worker works through them while the engine goes
    on. Their errors are raised by the next call that waits, or by ``flush``: a failed call is never
    silent, it is reported one step later.
    """

    def __init__(self):
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "") if env.get("PYTHONPATH") else root
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "pipeline.mlflow_worker"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
        )
        self._pending: list[str] = []  # ops sent whose replies are not read yet, oldest first
        self._uri = ""

    def open(self, uri: str, experiment: str) -> None:
        self._uri = uri
        self._send("init", {"uri": uri, "experiment": experiment})

    def _send(self, op: str, args: dict) -> None:
        try:
            self._proc.stdin.write(json.dumps({"op": op, "args": args}) + "\n")
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            self._exited()
        self._pending.append(op)

    def _exited(self):
        raise PipelineError("the MLflow tracking worker exited unexpectedly (see its messages above)")

    def _receive(self):
        """Read the replies of every op sent so far; the last one's result, or the first error."""
        result, error = None, None
        while self._pending:
            op = self._pending.pop(0)
            try:
                line = self._proc.stdout.readline()
            except OSError:
                line = ""
            if not line:
                self._exited()
            reply = json.loads(line)
            if not reply["ok"] and error is None:
                error = f"MLflow '{op}' failed: {reply['error']}"
                if op == "init":
                    error = f"cannot open MLflow tracking store {self._uri!r}: {error}"
            result = reply.get("result")
        if error is not None:
            raise PipelineError(error)
        return result

    def _call(self, op: str, **args):
        self._send(op, args)
        return self._receive()

    def create_run(self, run_name, tags, parent_id=None):
        return self._call("create_run", run_name=run_name, tags=tags, parent_id=parent_id)

    def log(self, run_id, metrics=None, params=None, tags=None):
        self._send("log", {"run_id": run_id, "metrics": metrics, "params": params, "tags": tags})

    def log_artifacts(self, run_id, directory):
        self._send("log_artifacts", {"run_id": run_id, "directory": directory})

    def log_dataset(self, run_id, name, digest, source):
        self._send("log_dataset", {"run_id": run_id, "name": name, "digest": digest, "source": source})

    def end(self, run_id, status="FINISHED"):
        self._send("end", {"run_id": run_id, "status": status})

    def find_recorded(self, digest):
        return self._call("find_recorded", digest=digest)

    def flush(self) -> None:
        """Wait until the worker has done every op sent so far; raise the first that failed."""
        self._receive()

    def close(self) -> None:
        """Let the worker finish what was sent (a failing run still gets its FAILED end), then stop it."""
        if self._proc.poll() is None:
            try:
                self._call("close")
            except PipelineError:
                pass  # already reported by flush on success; on failure the original error matters
            self._proc.stdin.close()
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()


def open_tracker(uri: str, experiment: str, in_process: bool | None = None):
    """A tracker for ``uri``; by default in-process if MLflow is already imported, else the worker."""
    if in_process is None:
        in_process = "mlflow" in sys.modules
    if in_process:
        return InProcessTracker(uri, experiment)
    worker = WorkerTracker()
    worker.open(uri, experiment)  # answered with the first create_run: a bad store fails before any stage
    return worker
