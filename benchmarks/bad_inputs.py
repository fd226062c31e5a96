"""Sweep of bad inputs across every ``tt`` command (issues 22 and 50): how many give a clear
one-line error, a traceback, a silent success, a misleading message or lost data (or a
leaked process), and which of the issues' classes of failure are fixed.

Runs the table of ``tests/bad_input_cases.py`` through the real CLI (typer's runner, in process),
its `SCENARIOS` (issue 50's second round: a full disk, ``-`` as stdout, a named pipe,
``tt designs`` over a user's files, ``tt train``'s run folder, a regenerated dataset, a killed
``tt generate --workers 2``, flags that do not apply, messages, ``tt predict`` on motions
shorter than the model's window, ``tt generate`` over a dataset whose root ``zarr.json`` is
damaged, ``tt.api.generate_dataset``'s messages) and the scenarios of issue 22
a table row cannot hold (resume from a damaged checkpoint, a resume with another learning
rate, ``tt view --serve`` under SIGTERM, detokenizing noisy tokens), each classified as
clear | ok (odd but valid input, handled) | traceback | misleading | silent | loss. Prints one
JSON line per case (``{"bench": "bad_inputs", ...}``) and writes
``benchmarks/results/bad_inputs.md``. Takes a few minutes (small `tt generate` datasets).

    python benchmarks/bad_inputs.py [--out benchmarks/results/bad_inputs.md]
"""

from __future__ import annotations

import argparse
import collections
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bad_input_cases import CASES, CLASSES, SCENARIOS, Case, Outcome, make_files, noisy_detokenized, outcome  # noqa: E402
from machine import machine_header  # noqa: E402


def _invoke(args: list[str]) -> tuple[int, str]:
    from typer.testing import CliRunner

    from tt.cli import app

    res = CliRunner().invoke(app, args)
    out = res.output + (res.stderr if res.stderr_bytes is not None else "")
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        out += f"\nTraceback (uncaught): {type(res.exception).__name__}: {res.exception}"  # the runner keeps it
    return res.exit_code, out


def _scenario(name: str, cls: int, run) -> Outcome:
    """A case that is a whole scenario: run() -> (kind, why)."""
    case = Case(name, cls, lambda f: [])
    try:
        kind, why = run()
    except Exception as e:  # the sweep reports, it does not stop
        kind, why = "traceback", f"{type(e).__name__}: {e}"
    return Outcome(case, kind, 0, "", why)


def _resume_fallback(files, work: Path):
    from tt.dit.checkpoint import list_checkpoints

    run = work / "run_fallback"
    base = [
        "train",
        "--data",
        files.episodes,
        "--size",
        "tiny",
        "--batch-size",
        "4",
        "--device",
        "cpu",
        "--out",
        str(run),
        "--config",
        "checkpoint_every=2",
    ]
    code, out = _invoke(base + ["--steps", "4"])
    if code:
        return "misleading", out
    latest = list_checkpoints(run)[-1]
    latest.write_bytes(latest.read_bytes()[:1000])
    code, out = _invoke(base + ["--steps", "6"])
    if "Traceback" in out:
        return "traceback", out
    if code:
        return "misleading", f"exit {code}: {out.strip()[-200:]}"
    if "resuming from the checkpoint before it" not in out:
        return "silent", "resumed without saying it fell back"
    return "ok", ""


def _resume_other_lr(files, work: Path):
    run = work / "run_lr"
    base = [
        "train",
        "--data",
        files.episodes,
        "--size",
        "tiny",
        "--batch-size",
        "4",
        "--device",
        "cpu",
        "--out",
        str(run),
    ]
    code, out = _invoke(base + ["--steps", "1", "--lr", "0.001"])
    if code:
        return "misleading", out
    code, out = _invoke(base + ["--steps", "2", "--lr", "0.002"])
    if code == 0:
        return "silent", "resumed with another learning rate"
    return ("clear", "") if "--lr" in out and "Traceback" not in out else ("misleading", out)


def _serve_sigterm(files, work: Path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "tt.cli", "view", files.designs + "#0", "--serve"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=work,
    )
    try:
        while (line := proc.stdout.readline()) and "serving" not in line:
            pass
        children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    finally:
        proc.kill()
    time.sleep(0.5)
    alive = [
        p
        for p in children
        if Path(f"/proc/{p}/stat").exists() and Path(f"/proc/{p}/stat").read_text().split(")")[-1].split()[0] != "Z"
    ]
    for p in alive:  # the sweep's own leftover: stop it
        subprocess.run(["kill", p], check=False)
    return ("loss", f"meshcat server {alive} left running") if alive else ("ok", "")


def _noisy_names(files, work: Path):
    for r in noisy_detokenized():
        if not r.ok and "repeated name" in r.error:
            return "misleading", r.error
    return "ok", ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "bad_inputs.md")
    args = parser.parse_args()

    from tt.generate import GenerateConfig, generate

    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        dataset = work / "ds"
        generate(
            GenerateConfig(
                space="viperx", designs=4, episodes_per_design=1, designs_per_shard=2, min_steps=10, max_motion_steps=24
            ),
            dataset,
            device="cpu",
            progress=False,
        )
        files = make_files(work / "files", dataset)
        results = [outcome(c, files, _invoke) for c in CASES]
        for k, s in enumerate(SCENARIOS):
            folder = work / f"scenario_{k:02d}"
            folder.mkdir()
            results.append(_scenario(s.name, s.cls, lambda s=s, folder=folder: s.run(files, folder)))
        for name, cls, run in (
            ("train: resume when the latest checkpoint is truncated", 2, _resume_fallback),
            ("train: resume with another --lr", 4, _resume_other_lr),
            ("view --serve stopped by SIGTERM", 5, _serve_sigterm),
            ("detokenize: noisy quadruped tokens (sigma 0.3, 1, 3)", 7, _noisy_names),
        ):
            results.append(_scenario(name, cls, lambda run=run: run(files, work)))
        for r in results:
            print(
                json.dumps(
                    {
                        "bench": "bad_inputs",
                        "case": r.case.name,
                        "class": r.case.cls,
                        "outcome": r.kind,
                        "exit": r.code,
                        "why": r.why[:200],
                    }
                )
            )
    seconds = time.perf_counter() - start

    counts = collections.Counter(r.kind for r in results)
    by_class = collections.defaultdict(list)
    for r in results:
        by_class[r.case.cls].append(r)
    fixed = [c for c in CLASSES if by_class[c] and all(r.kind in ("clear", "ok") for r in by_class[c])]
    lines = [
        "# Bad-input sweep (issues 22 and 50)",
        "",
        machine_header("cpu").rstrip(),
        f"- sweep time: {seconds:.0f} s",
        "",
        f"{len(results)} cases across every command; `python benchmarks/bad_inputs.py` reruns it "
        "(`tests/test_bad_inputs.py` asserts the same table).",
        "",
        "| outcome | cases |",
        "|---|---:|",
    ]
    for kind, label in (
        ("clear", "clear one-line error naming the file, flag or field"),
        ("ok", "odd but valid input, handled"),
        ("traceback", "traceback or internal error"),
        ("misleading", "misleading message"),
        ("silent", "success reported for a bad input or garbage output"),
        ("loss", "data lost or a process leaked"),
    ):
        lines.append(f"| {label} | {counts.get(kind, 0)} |")
    lines += [
        "",
        f"Classes of failure of the issues fixed: {len(fixed)} of {len(CLASSES)} (every case of the class "
        "clear or handled).",
        "",
        "| class | cases | clear or handled | fixed |",
        "|---|---:|---:|---|",
    ]
    for c, label in CLASSES.items():
        rs = by_class[c]
        good = sum(r.kind in ("clear", "ok") for r in rs)
        lines.append(f"| {c}. {label} | {len(rs)} | {good} | {'yes' if c in fixed else 'no'} |")
    lines += ["", "## Cases", "", "| class | case | outcome | note |", "|---:|---|---|---|"]
    for r in results:
        lines.append(f"| {r.case.cls} | {r.case.name} | {r.kind} | {r.why.replace('|', '/')[:120]} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}: {dict(counts)}; classes fixed {len(fixed)}/{len(CLASSES)}")


if __name__ == "__main__":
    main()
