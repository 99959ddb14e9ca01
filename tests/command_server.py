"""Runs the project's and nerfstudio's console commands for the tests, each in a process of its own, without paying
their imports each time.

A nerfstudio command spends about 22 s of CPU before it reads its arguments (`ns-eval --help`, idle): importing
torch, and nerfstudio's ``method_configs``, whose ``get_external_methods`` calls ``inspect.stack()`` 26 times, each
walking the thousands of loaded modules. This server pays that once: it imports them, then forks one child per
request. The child becomes the command: its own session, folder, environment, ``sys.argv`` and standard streams,
then the console script's entry point (``importlib.metadata``'s ``console_scripts``, which is what the installed
``ns-*`` script calls), and a normal interpreter exit (atexit handlers, non-daemon threads) with the command's exit
status.

Protocol, one JSON line each way per request on stdin/stdout: ``{"argv", "cwd", "env", "stdout", "stderr",
"timeout"}`` in; ``{"returncode", "timed_out"}`` out, once the command has ended or, after ``timeout`` seconds, its
process group has been killed.
"""

from __future__ import annotations

import json
import os
import select
import signal
import sys
from importlib.metadata import entry_points
from typing import Callable, Dict

PRELOADED = ("torch", "nerfstudio.configs.method_configs", "gear_nerfstudio")
"""What every command imports first (the costly part), imported once here."""


def run_child(request: dict, entrypoint: Callable[[], object]) -> None:
    """Become the requested command; raises SystemExit with its status (never returns)."""
    os.setsid()  # the command and what it starts form one group, which the caller can stop
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    for fd, path in ((1, request["stdout"]), (2, request["stderr"])):
        out = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(out, fd)
        os.close(out)
    sys.argv = list(request["argv"])
    sys.exit(entrypoint())


def serve() -> None:
    scripts = {ep.name: ep for ep in entry_points(group="console_scripts")}
    loaded: Dict[str, Callable[[], object]] = {}
    for line in sys.stdin:
        request = json.loads(line)
        name = os.path.basename(request["argv"][0])
        if name not in loaded:
            loaded[name] = scripts[name].load()  # imported here, so that the next request's child has it too
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            run_child(request, loaded[name])
        ended = os.pidfd_open(pid)  # readable once the child has ended
        timed_out = not select.select([ended], [], [], request["timeout"])[0]
        os.close(ended)
        if timed_out:
            os.killpg(pid, signal.SIGKILL)
        status = os.waitpid(pid, 0)[1]
        print(json.dumps({"returncode": os.waitstatus_to_exitcode(status), "timed_out": timed_out}), flush=True)


if __name__ == "__main__":
    for module in PRELOADED:
        __import__(module)
    serve()
