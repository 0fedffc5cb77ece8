"""A fork server for the tests' commands: ``python train.py ...`` without paying its imports.

A command of the project (``python train.py``, ``python -m generalist_control.evaluate``, a
script of ``benchmarks/``) spends 3 to 7 s of CPU importing torch, Lightning, MLflow and
python-control before its first line of work, and the suite runs dozens of them. This
process imports them once; for each request it forks a child that becomes the command: its
own process with the request's working directory, environment, ``sys.argv`` and
``sys.path[0]``, standard streams on the given files, the script run as ``__main__``, exit
handlers run and its exit status reported. Only the interpreter's start and the imports are
shared. Used through :func:`helpers.run_command`; tests about processes themselves (signals,
process groups, what loads when) start real ones.

Protocol, one JSON object a line: request ``{"argv", "cwd", "env", "stdout", "stderr"}``
(``argv`` without the interpreter), answers ``{"pid"}`` when forked, then ``{"rc"}``.
"""

from __future__ import annotations

import json
import os
import sys
import threading

#: What the project's commands import before their work (their common, costly part).
PRELOAD = (
    "torch",
    "lightning",
    "mlflow",
    "control",
    "generalist_control.train",
    "generalist_control.evaluate",
    "generalist_control.training.fit",
    # imported during the work, 1-1.4 s each: the optimizer's first construction imports
    # torch._dynamo; opening an SQLite store, MLflow's SQLAlchemy store; evaluate, ONNX
    "torch._dynamo",
    "mlflow.store.tracking.sqlalchemy_store",
    "torch.onnx",
    "onnxruntime",
    "pyarrow.dataset",
)


def _become(request: dict) -> int:
    """In the forked child: run the request's command; its exit status."""
    import atexit
    import runpy
    import traceback

    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    stdin = os.open(os.devnull, os.O_RDONLY)
    os.dup2(stdin, 0)
    for fd, path in ((1, request["stdout"]), (2, request["stderr"])):
        os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), fd)
    argv = request["argv"]
    for entry in reversed(request["env"].get("PYTHONPATH", "").split(os.pathsep)):
        if entry and entry not in sys.path:
            sys.path.insert(1, entry)
    rc = 0
    try:
        if argv[0] == "-m":
            sys.argv = [argv[1], *argv[2:]]
            sys.path[0] = os.getcwd()
            sys.modules.pop(argv[1], None)  # run afresh as __main__, as ``python -m`` does
            runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
        else:
            sys.argv = list(argv)
            sys.path[0] = os.path.dirname(os.path.abspath(argv[0]))
            runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as stop:
        if stop.code is None:
            rc = 0
        elif isinstance(stop.code, int):
            rc = stop.code
        else:
            print(stop.code, file=sys.stderr)
            rc = 1
    except KeyboardInterrupt:
        traceback.print_exc()
        rc = 130
    except BaseException:  # noqa: BLE001 - reported as the interpreter reports it
        traceback.print_exc()
        rc = 1
    threading._shutdown()  # type: ignore[attr-defined]  # as the interpreter does at exit
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    return rc


def serve() -> None:
    """Answer requests on stdin until it closes; one child at a time."""
    channel = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # nothing the imports print reaches the channel
    for name in PRELOAD:
        __import__(name)
    alone = threading.active_count() == 1
    channel.write(json.dumps({"ready": alone}) + "\n")
    for line in sys.stdin:
        request = json.loads(line)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            os.close(channel.fileno())
            rc = 1
            try:
                rc = _become(request)
            finally:
                os._exit(rc)
        channel.write(json.dumps({"pid": pid}) + "\n")
        _, status = os.waitpid(pid, 0)
        channel.write(json.dumps({"rc": os.waitstatus_to_exitcode(status)}) + "\n")


if __name__ == "__main__":
    serve()
