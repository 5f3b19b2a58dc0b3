"""What the side-by-side benchmarks against LeRobot's PyTorch share (`bench_smolvla_full.py`,
`bench_pi_full.py`): the machine's description, a process's memory from /proc, and running a
measuring command (a `kairos predict --repeat`, or another Python process) as a child whose last
stdout line is JSON, with the child's peak RSS taken from the kernel when it exits.

Stdlib only: the π benchmark's parent process imports no torch.
"""

import json
import os
import platform
import shlex
import statistics
import subprocess
from pathlib import Path

# libgomp reads this when torch loads it. PASSIVE: a waiting OpenMP thread sleeps instead of
# spinning. On a shared machine a spinning thread whose partner is descheduled burns CPU time
# doing nothing (several times the CPU time of the work itself), which makes the CPU-time
# column meaningless; on an idle machine the two policies differ by little. Set
# OMP_WAIT_POLICY yourself to override. Children inherit it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def status_kb(field, pid="self"):
    """One `Vm*` field of /proc/PID/status in kB (0 if absent)."""
    for line in open(f"/proc/{pid}/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def reset_peak_rss():
    """Make this process's VmHWM its current VmRSS (Linux: `5` to /proc/self/clear_refs)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def machine_line(extra=""):
    """`# CPU [flags], cores; extra, python X`: what a benchmark's numbers were measured on."""
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
    flags = next((ln.split(":", 1)[1].split() for ln in open("/proc/cpuinfo") if ln.startswith("flags")), [])
    want = ("avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "amx_bf16")
    return (f"# {cpu} [{' '.join(f for f in want if f in flags)}], {os.cpu_count()} cores; {extra}"
            f"OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']}, python {platform.python_version()}")


def safetensors_header(path):
    """`{name: {"dtype", "shape", "data_offsets"}}` from a safetensors file's header (no tensor read)."""
    with open(path, "rb") as f:
        n = int.from_bytes(f.read(8), "little")
        header = json.loads(f.read(n))
    header.pop("__metadata__", None)
    return header


def run_json(cmd, cwd, shell=False):
    """Run `cmd`, stderr passed through; its last stdout line parsed as JSON, plus
    `child_peak_rss_mb`: the child's peak RSS (`ru_maxrss`, whatever it measures itself)."""
    proc = subprocess.Popen(cmd, shell=shell, cwd=cwd, stdout=subprocess.PIPE, text=True)
    out = proc.stdout.read()
    proc.stdout.close()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        shown = cmd if isinstance(cmd, str) else shlex.join(str(c) for c in cmd)
        raise subprocess.CalledProcessError(proc.returncode, shown, out)
    lines = out.strip().splitlines()
    if not lines:
        raise RuntimeError(f"no output from {cmd}")
    result = json.loads(lines[-1])
    result["child_peak_rss_mb"] = usage.ru_maxrss / 1024
    return result


def time_kairos(template, model, batch, threads, iters, cwd: Path, **fields):
    """Run a Kairos command template once (see the benchmarks' docstrings) and summarise it.

    `kairos predict --repeat`'s JSON keeps its timings (not its actions): `median_ms`, `runs`,
    `cpu_ms_per_run`, `rss_mb` (its own VmHWM), `stages_ms_last`, and `model_rss_mb` if it
    reports one. Any other JSON (`median_ms`, ...) is returned as it is.
    """
    cmd = template.format(model=shlex.quote(str(model)), batch=batch, threads=threads, iters=iters, **fields)
    result = run_json(cmd, cwd, shell=True)
    if "runs_ms" in result:
        runs = result["runs_ms"]
        summary = {
            "median_ms": round(statistics.median(runs), 1),
            "runs": [round(r) for r in runs],
            "cpu_ms_per_run": round(result["cpu_ms_per_run"]),
            "rss_mb": round(result["peak_rss_mb"]),
            "stages_ms_last": {k: round(v) for k, v in result["timing_ms"].items()},
        }
        if "model_rss_mb" in result:
            summary["model_rss_mb"] = round(result["model_rss_mb"])
        if "paths" in result:
            summary["paths"] = result["paths"]
        result = summary
    return result
