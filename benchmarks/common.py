"""What the benchmarks share: paths, child commands, the timed ns-train child, the machine line, pages."""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "data" / "real"
"""The real captures (``../shared/data/real`` next to the repository; ``SOURCES.md`` there)."""
BIN = Path(sys.executable).parent
"""The bin folder of the Python running the benchmark: the project's virtual environment."""
TRAIN_CHILD = "_train"
"""First argument of ``python -m benchmarks`` in the child process that runs ns-train with timing hooks."""


def command_environment() -> Dict[str, str]:
    """os.environ with ``BIN`` first on PATH and this package's folder last on PYTHONPATH (for the child)."""
    paths = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p] + [str(Path(__file__).parents[1])]
    path = f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"
    return {**os.environ, "PATH": path, "PYTHONPATH": os.pathsep.join(paths)}


def ns(*args: str, log: Optional[Path] = None) -> None:
    """Run an ns-* command (the environment's, else the first on PATH); its output to ``log`` when given."""
    environment = command_environment()
    command = [shutil.which(args[0], path=environment["PATH"]) or args[0], *args[1:]]
    if log is None:
        subprocess.run(command, check=True, env=environment)
        return
    with open(log, "w") as handle:
        subprocess.run(command, check=True, env=environment, stdout=handle, stderr=subprocess.STDOUT)


def run_measured(command: Sequence[str], log: Path) -> resource.struct_rusage:
    """Run ``command`` with its output to ``log``; its resource usage (``os.wait4``: ``ru_maxrss`` in KiB)."""
    with open(log, "w") as handle:
        child = subprocess.Popen(list(command), stdout=handle, stderr=subprocess.STDOUT, env=command_environment())
        _, status, usage = os.wait4(child.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(map(str, command))} failed; see {log}")
    return usage


def timed_train(arguments: Sequence[str], timing: Path, log: Path):
    """ns-train ``arguments`` in a child process with ``train_child``'s hooks; (its timing record, its usage)."""
    usage = run_measured([sys.executable, "-P", "-m", "benchmarks", TRAIN_CHILD, str(timing), *arguments], log)
    return json.loads(timing.read_text()), usage


def train_child(timing_path: Path, arguments: List[str]) -> None:
    """Child process: ns-train with hooks that write to ``timing_path`` each checkpoint's wall-clock and CPU seconds of
    training (checkpoint writes left out), the totals and each iteration's seconds."""
    from nerfstudio.engine.trainer import Trainer
    from nerfstudio.scripts.train import entrypoint

    state: Dict[str, Any] = {"start": None, "saving": 0.0, "cpu_saving": 0.0, "checkpoints": {}, "iterations": []}
    train, iteration, save = Trainer.train, Trainer.train_iteration, Trainer.save_checkpoint

    def timed_train(self) -> None:
        state["start"], state["cpu_start"] = time.perf_counter(), time.process_time()
        train(self)
        checkpoints = [{"step": step, **times} for step, times in sorted(state["checkpoints"].items())]
        timing = {
            "train_seconds": checkpoints[-1]["seconds"] if checkpoints else None,
            "train_cpu_seconds": checkpoints[-1]["cpu_seconds"] if checkpoints else None,
            "checkpoints": checkpoints,
            "iteration_seconds": state["iterations"],
        }
        timing_path.write_text(json.dumps(timing, indent=1))

    def timed_iteration(self, step: int):
        entered = time.perf_counter()
        result = iteration(self, step)
        state["iterations"].append(time.perf_counter() - entered)
        return result

    def timed_save(self, step: int) -> None:
        entered, cpu_entered = time.perf_counter(), time.process_time()
        if state["start"] is not None:  # the final save repeats the last step's save: keep the first
            state["checkpoints"].setdefault(int(step), {
                "seconds": entered - state["start"] - state["saving"],
                "cpu_seconds": cpu_entered - state["cpu_start"] - state["cpu_saving"],
            })  # fmt: skip
        save(self, step)
        state["saving"] += time.perf_counter() - entered
        state["cpu_saving"] += time.process_time() - cpu_entered

    Trainer.train, Trainer.train_iteration, Trainer.save_checkpoint = timed_train, timed_iteration, timed_save
    sys.argv = ["ns-train", *arguments]
    entrypoint()


def machine_description(device: str = "cpu") -> str:
    """CPU model, cores, memory, OS, Python, torch, and the GPU when CUDA is used."""
    import torch

    cpu = platform.processor() or platform.machine()
    lscpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout if shutil.which("lscpu") else ""
    cpu = next((line.split(":", 1)[1].strip() for line in lscpu.splitlines() if line.startswith("Model name:")), cpu)
    memory = next((f", {int(line.split()[1]) / 1024**2:.0f} GiB RAM" for line in Path("/proc/meminfo").read_text()
                   .splitlines() if line.startswith("MemTotal:")), "") if Path("/proc/meminfo").is_file() else ""
    text = (f"{cpu}, {os.cpu_count()} logical CPUs{memory}; {platform.platform()}; Python {platform.python_version()}, "
            f"torch {torch.__version__} with {torch.get_num_threads()} CPU thread(s) per process")
    if device == "cuda" and torch.cuda.is_available():
        properties = torch.cuda.get_device_properties(0)
        text += f"; GPU {properties.name} ({properties.total_memory / 1024**3:.0f} GiB), CUDA {torch.version.cuda}"
    return text


def timed(function: Callable[[], Any], repeats: int, synchronize: Callable[[], None] = lambda: None):
    """(median seconds, last result) of ``repeats`` calls, ``synchronize`` at both ends of each."""
    times, result = [], None
    for _ in range(repeats):
        synchronize()
        start = time.perf_counter()
        result = function()
        synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def read_mask(masks: Path, camera: str, number: int) -> np.ndarray:
    """A real capture's foreground mask (``moving_region.mask_path``) as an (H, W) bool map."""
    from PIL import Image

    from gear_nerfstudio.model.moving_region import mask_path

    return np.array(Image.open(mask_path(masks, camera, number)).convert("L")) > 127


def gear_mask_counts(levels: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """Gear map (Eq 5 levels, H x W) against moving pixels: [moving at gear >= 2, moving, others at gear 1, others]."""
    return np.array([(levels[moving] >= 2).sum(), moving.sum(), (levels[~moving] == 1).sum(), (~moving).sum()])


def pct(value: Optional[float]) -> str:
    """A share as a percentage with one decimal, "n/a" for None."""
    return "n/a" if value is None else f"{100 * value:.1f}"


def mean(values: List[Tuple[float, ...]], index: int) -> Optional[float]:
    """Mean of one field of tuples, None for none."""
    return float(np.mean([v[index] for v in values])) if values else None


def provenance(machine: str) -> List[str]:
    """The lines naming this benchmark's command as typed (``python -m benchmarks <subcommand> [options]``) and the
    machine."""
    return [f"Command: `python -m benchmarks {shlex.join(sys.argv[1:])}`", "", f"Machine: {machine}."]


def page(title: str, lines: Sequence[str], device: str = "cpu") -> str:
    """A results page: the title, the command, the date and the machine, then ``lines``."""
    today = datetime.date.today().isoformat()
    return "\n".join([f"# {title}", "", *provenance(f"{machine_description(device)}; {today}"), "", *lines, ""])


def table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> List[str]:
    """A Markdown table's lines: the header, its rule, a line per row."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(map(str, row)) + " |" for row in rows]


def fill_page(path: Path, parts: Dict[str, str]) -> None:
    """Write each of ``parts`` into a hand-kept page between its lines ``<!-- NAME -->`` and ``<!-- /NAME -->`` (a
    missing page: the parts alone)."""
    text = path.read_text() if path.is_file() else "".join(f"<!-- {n} -->\n<!-- /{n} -->\n\n" for n in parts)
    for name, part in parts.items():
        text = re.sub(rf"(?s)(<!-- {name} -->\n).*?(<!-- /{name} -->)", lambda m: f"{m[1]}{part}\n{m[2]}", text)
    path.write_text(text)


def write_report(text: str, *paths: Optional[Path], append: bool = False) -> None:
    """Print ``text`` and write (or append) it to each of ``paths`` that is not None."""
    print(text)
    for path in filter(None, paths):
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("a" if append else "w") as handle:
            handle.write(text)
