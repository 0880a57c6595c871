#!/usr/bin/env python
"""The project's check of one OpenCL device: its self-test, the test suite and the three benches.

Made for the machines with a GPU that some sessions are lent (issue 14): one
command runs everything on the named device and writes what it found into one
folder, to be committed with the session's work.

    .venv/bin/python bench/device_check.py --device nvidia [--out DIR] [--full]
        [--tests-timeout 600] [--bench-timeout 300] [--per-test-timeout 60]
        [--pytest-args '-n 12']

Steps, each in its own process with ``LBVH_DEVICE`` set to the device and a
time limit; a step that fails or runs out of time is recorded and the next
one runs:

1. ``lbvh devices`` (every device, its self-test result, the one chosen);
2. the test suite, ``pytest -q`` (as the README's test command runs it);
3. ``bench/bench_build.py --quick``, ``bench/bench_traverse.py --quick`` and
   ``bench/bench_builders.py --quick --no-peers`` (``--full``: their default
   sizes, tens of minutes).

The folder (default ``bench/results/device-<device>``) receives ``summary.md``
(device facts, each step's command, exit status and seconds), one ``.log``
per step, and the benches' own Markdown and JSON. The exit status is 0 only if
every step passed.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:60] or "device"


def device_facts(name: str) -> dict:
    """What the device reports of itself (read from the device, never assumed)."""
    sys.path.insert(0, str(REPO))
    import pyopencl as cl
    from lbvh.device import describe, find_device

    dev = find_device(name)
    facts = {"device": describe(dev), "driver": dev.driver_version.strip(),
             "type": cl.device_type.to_string(dev.type), "compute_units": dev.max_compute_units,
             "global_mem_bytes": dev.global_mem_size, "max_alloc_bytes": dev.max_mem_alloc_size,
             "local_mem_bytes": dev.local_mem_size, "max_work_group_size": dev.max_work_group_size,
             "host": f"{platform.node()} {platform.machine()} {platform.processor()}".strip(),
             "python": sys.version.split()[0]}
    return facts


def run_step(name: str, command: list[str], out: Path, env: dict, timeout: int) -> dict:
    log = out / f"{name}.log"
    start = time.perf_counter()
    with open(log, "w") as f:
        f.write("$ " + " ".join(command) + "\n")
        f.flush()
        try:
            proc = subprocess.run(command, cwd=REPO, env=env, stdout=f, stderr=subprocess.STDOUT,
                                  timeout=timeout)
            status = proc.returncode
        except subprocess.TimeoutExpired:
            status = "timeout"
    seconds = time.perf_counter() - start
    tail = log.read_text().strip().splitlines()[-1:] or [""]
    print(f"{name}: {'ok' if status == 0 else status} in {seconds:.0f} s  ({tail[0][:100]})",
          flush=True)
    return {"step": name, "command": " ".join(command), "status": status,
            "seconds": round(seconds, 1), "last_line": tail[0], "log": log.name}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default=os.environ.get("LBVH_DEVICE"),
                   help="device name, a substring of 'platform / device' (default $LBVH_DEVICE)")
    p.add_argument("--out", type=Path, default=None, help="output folder")
    p.add_argument("--full", action="store_true", help="the benches at their default sizes")
    p.add_argument("--tests-timeout", type=int, default=600)
    p.add_argument("--bench-timeout", type=int, default=300)
    p.add_argument("--skip-tests", action="store_true")
    p.add_argument("--per-test-timeout", type=int, default=60,
                   help="seconds a test may take where pytest-timeout is installed (0: none)")
    p.add_argument("--pytest-args", default="",
                   help="more arguments for pytest, one string (say '-n 12 -v' on a machine "
                        "with more cores: the suite's default is two workers)")
    args = p.parse_args(argv)
    if not args.device:
        p.error("name a device with --device (see `lbvh devices`)")
    facts = device_facts(args.device)
    out = args.out or HERE / "results" / f"device-{_slug(facts['device'])}"
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, LBVH_DEVICE=args.device)
    py = sys.executable
    quick = [] if args.full else ["--quick"]
    steps = [("devices", [py, "-m", "lbvh.cli", "devices"], 300)]
    if not args.skip_tests:
        # the failures' one-line reasons at the end, and (where pytest-timeout is
        # installed) a limit per test, so that one slow test cannot keep the run from
        # printing them before --tests-timeout
        limit = (["--timeout", str(args.per_test_timeout)]
                 if args.per_test_timeout and importlib.util.find_spec("pytest_timeout") else [])
        steps.append(("tests", [py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rfE",
                                "--tb=line", *limit, *shlex.split(args.pytest_args)],
                      args.tests_timeout))
    steps += [
        ("bench_build", [py, "bench/bench_build.py", *quick, "--no-peers",
                         "--json", str(out / "bench_build.json")], args.bench_timeout),
        ("bench_traverse", [py, "bench/bench_traverse.py", *quick, "--no-peers",
                            "--out", str(out / "traverse")], args.bench_timeout),
        ("bench_builders", [py, "bench/bench_builders.py", *quick, "--no-peers",
                            "--out", str(out / "builders")], args.bench_timeout),
    ]
    results = [run_step(name, command, out, env, timeout) for name, command, timeout in steps]
    (out / "summary.json").write_text(json.dumps({"facts": facts, "steps": results}, indent=1))
    lines = [f"# Device check: {facts['device']}", "",
             f"`{' '.join([Path(py).name, 'bench/device_check.py', *sys.argv[1:]])}`, "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}", "",
             "| fact | value |", "|---|---|"]
    lines += [f"| {k} | {str(v).replace('|', '/')} |" for k, v in facts.items()]
    lines += ["", "| step | status | seconds | last line |", "|---|---|---:|---|"]
    lines += [f"| [{r['step']}]({r['log']}) | {'ok' if r['status'] == 0 else r['status']} | "
              f"{r['seconds']} | {r['last_line'][:120].replace('|', '/')} |" for r in results]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'summary.md'}")
    return 0 if all(r["status"] == 0 for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
