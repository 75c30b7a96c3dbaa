"""The tracking worker: a child process that imports MLflow and performs ``MlflowOps`` calls sent as
JSON lines on stdin, answering one JSON line each on stdout.

Why a process: importing MLflow and its SQL store takes seconds and hundreds of modules. In the worker, the
engine's own process never imports it, and the calls it only posts (log, end, artifacts) run while the next
stage computes. The worker starts when the engine has something to log: an all-hit run that is already
recorded (``pipeline.run_record``) starts none.
"""

from __future__ import annotations

import json
import os
import sys

from pipeline.mlflow_ops import MlflowOps


def _prewarm() -> None:
    """Import what the first request will need; the SQL store only if the URI will likely be sqlite."""
    import mlflow.tracking  # noqa: F401

    uri = os.environ.get("MLFLOW_TRACKING_URI", "sqlite:")
    if uri.startswith("sqlite:"):
        import mlflow.store.tracking.sqlalchemy_store  # noqa: F401


def serve(requests, replies) -> None:
    ops = None
    for line in requests:
        request = json.loads(line)
        op, args = request["op"], request.get("args", {})
        try:
            if op == "close":
                replies.write(json.dumps({"ok": True, "result": None}) + "\n")
                replies.flush()
                return
            if op == "init":
                ops = MlflowOps(**args)
                result = ops.experiment_id
            elif ops is None:
                raise RuntimeError(f"'{op}' before 'init'")
            else:
                result = getattr(ops, op)(**args)
            reply = {"ok": True, "result": result}
        except Exception as exc:  # reported to the engine, which raises a PipelineError
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        replies.write(json.dumps(reply) + "\n")
        replies.flush()


def main() -> None:
    # Keep the protocol channel clean: anything a library prints goes to stderr.
    replies = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1)
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    _prewarm()
    serve(sys.stdin, replies)
    # Every call has committed by now: skip tearing down MLflow's modules, which the engine waits for.
    sys.stderr.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
