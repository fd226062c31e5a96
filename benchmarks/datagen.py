"""Data generation throughput: ViperX episodes per second end to end (designs, rollout,
scoring, tokenization, zarr writes), with the share of time per stage.

Runs `tt.generate.generate` on shards of N designs x 10 episodes (the paper's
episodes per design) on full training motions:
  serial: one process, `--shards-serial` shards (the Warp modules are loaded before timing), once
          per `--threads` count of its Warp rollouts (default: every core);
  cmaes: the same with the paper's data biasing (CMA-ES, population 5, 3 generations per run);
  ray: a local Ray cluster of `--workers` workers, `--workers` shards at once (worker start-up,
       imports and Warp module loading included: what a fresh `tt generate --ray local` pays).
Prints one JSON line per run and writes benchmarks/results/datagen.md. Usage:
    python benchmarks/datagen.py [--designs-per-shard 1024] [--workers 2] [--threads 1 2] [--out /tmp/datagen]
        [--name datagen]   # writes benchmarks/results/<name>.md, appends to runs/benchmarks/<name>.jsonl
    python benchmarks/datagen.py --table-only   # rebuild the table from the JSON lines of earlier runs
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import time
from pathlib import Path

try:
    from machine import machine_header
except ImportError:  # run as a module from the repository root
    from benchmarks.machine import machine_header

from tt.generate import STAGES, GenerateConfig, generate

RESULTS = Path(__file__).parent / "results"
#: Logs of runs: outside the repository's tree of results (runs/ is not tracked).
RUNS = Path(__file__).resolve().parents[1] / "runs" / "benchmarks"


def _cpu_seconds() -> float:
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def run(mode: str, config: GenerateConfig, out: Path, workers: int, threads: int | None = None) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    load0 = os.getloadavg()[0]
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    report = generate(
        config,
        out,
        device="cpu",
        workers=workers,
        ray_address="local" if mode == "ray" else None,
        progress=True,
        threads=threads,
    )
    wall = time.perf_counter() - t0
    stages = {s: sum(r["seconds"][s] for r in report.shard_results) for s in STAGES}
    t = report.totals
    row = {
        "mode": mode,
        "workers": workers,
        "threads": threads,
        "bias": config.bias,
        "designs": config.designs,
        "designs_per_shard": config.designs_per_shard,
        "generated": t["generated"],
        "kept": t["kept"],
        "dropped": t["dropped"],
        "steps": t["steps"],
        "bytes": t["bytes"],
        "wall_s": wall,
        "episodes_per_s": t["generated"] / wall,
        "kept_per_s": t["kept"] / wall,
        # CPU seconds of the processes that generated the shards (Ray workers included):
        # the machine is shared, so CPU time per episode is the comparable figure.
        "cpu_s_shards": report.run["cpu_seconds"],
        "cpu_s_this_process_tree": _cpu_seconds() - cpu0,
        "stage_s": stages,
        "loadavg_start": load0,
        "loadavg_end": os.getloadavg()[0],
    }
    print("datagen " + json.dumps(row), flush=True)
    return row


def table(rows: list[dict]) -> str:
    lines = [
        "| run | designs (per shard) | episodes generated | kept | steps kept | wall [s] | episodes/s | kept/s | "
        "CPU [ms] / episode | " + " | ".join(STAGES) + " | size | load avg (start / end) |",
        "|---|---|---|---|---|---|---|---|---|" + "---|" * len(STAGES) + "---|---|",
    ]
    for r in rows:
        total = sum(r["stage_s"].values()) or 1.0
        shares = " | ".join(f"{100 * r['stage_s'][s] / total:.1f} %" for s in STAGES)
        name = "1 process" if r["mode"] == "serial" else f"Ray, {r['workers']} workers"
        if r.get("threads"):
            name += f", {r['threads']} rollout thread{'s' if r['threads'] > 1 else ''}"
        name += ", --bias cmaes" if r.get("bias") else ""
        name += f" ({r['note']})" if r.get("note") else ""
        lines.append(
            f"| {name} | {r['designs']} ({r['designs_per_shard']}) | {r['generated']:,} | {r['kept']:,} | "
            f"{r['steps']:,} | {r['wall_s']:.0f} | {r['episodes_per_s']:.1f} | {r['kept_per_s']:.1f} | "
            f"{1000 * r['cpu_s_shards'] / r['generated']:.2f} | {shares} | "
            f"{r['bytes'] / 2**20:.0f} MiB | {r['loadavg_start']:.1f} / {r['loadavg_end']:.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--designs-per-shard", type=int, default=1024)
    ap.add_argument("--shards-serial", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--episodes-per-design", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("/tmp/tt_datagen"))
    ap.add_argument("--skip", choices=("serial", "ray", "cmaes"), action="append", default=[])
    ap.add_argument(
        "--threads",
        type=int,
        nargs="+",
        default=[None],
        help="rollout threads of the serial runs, one run per count (default: every core)",
    )
    ap.add_argument("--note", default="", help="a note shown with this invocation's rows")
    ap.add_argument("--name", default="datagen", help="results file stem: benchmarks/results/<name>.md")
    ap.add_argument(
        "--log",
        type=Path,
        default=None,
        help="JSON lines of every run, appended (default runs/benchmarks/<name>.jsonl)",
    )
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument(
        "--full-run",
        type=Path,
        default=None,
        help="log of a large run whose last line is 'RESULT {json}' (see full_run below), added as a section",
    )
    args = ap.parse_args()
    args.log = args.log or RUNS / f"{args.name}.jsonl"

    rows = []
    if not args.table_only:
        base = GenerateConfig(
            space="viperx",
            designs=args.designs_per_shard,
            episodes_per_design=args.episodes_per_design,
            seed=args.seed,
            designs_per_shard=args.designs_per_shard,
        )
        # Load the Warp modules of every ViperX topology outside the timed runs.
        warm = GenerateConfig(
            space="viperx",
            designs=24,
            episodes_per_design=1,
            designs_per_shard=24,
            min_steps=20,
            max_motion_steps=20,
            seed=12345,
        )
        shutil.rmtree(args.out / "warm", ignore_errors=True)
        generate(warm, args.out / "warm", device="cpu", progress=False)
        if "serial" not in args.skip:
            cfg = GenerateConfig(**{**base.__dict__, "designs": args.shards_serial * args.designs_per_shard})
            for threads in args.threads:
                rows.append(run("serial", cfg, args.out / "serial", 1, threads))
        if "cmaes" not in args.skip:
            cfg = GenerateConfig(**{**base.__dict__, "bias": "cmaes", "seed": args.seed + 2})
            rows.append(run("serial", cfg, args.out / "cmaes", 1))
        if "ray" not in args.skip:
            cfg = GenerateConfig(
                **{**base.__dict__, "designs": args.workers * args.designs_per_shard, "seed": args.seed + 1}
            )
            rows.append(run("ray", cfg, args.out / "ray", args.workers))
        args.log.parent.mkdir(parents=True, exist_ok=True)
        with open(args.log, "a") as f:
            for r in rows:
                r["note"] = args.note
                r["command"] = "python benchmarks/datagen.py " + " ".join(sys.argv[1:])
                f.write(json.dumps(r) + "\n")
    rows = [json.loads(line) for line in open(args.log)] if args.log.exists() else rows
    md = [
        "# Data generation throughput (`tt generate`, ViperX)",
        "",
        machine_header("cpu"),
        "End to end: design sampling, batched Warp rollout (128 designs x 10 augmented training motions per launch "
        "group), scoring, tokenization of every executed step, zarr writes with checksums. 10 episodes per design, "
        "full training motions (220-370 steps at 50 Hz), episodes shorter than 100 steps dropped. "
        "Stage shares are of the summed stage times of all shards (per worker). "
        "The machine is shared: the load average shows how many other jobs competed for its cores.",
        "",
        table(rows),
        "",
    ]
    commands = list(dict.fromkeys(r["command"] for r in rows if r.get("command")))
    if commands:
        md += ["Commands: " + "; ".join(f"`{c}`" for c in commands), ""]
    if rows:
        best = min(r["cpu_s_shards"] / r["generated"] for r in rows if not r.get("bias"))
        md += [
            f"Reading: wall-clock rates depend on what else ran (load averages of 2-5 on these 2 cores); the CPU "
            f"time per episode does not. At {1000 * best:.1f} ms of CPU per episode, an idle core generates about "
            f"{1 / best:.0f} episodes/s, so 2 idle cores about {2 / best:.0f}/s. The Ray rows include starting the "
            "local cluster and its workers (imports, Warp module loading). `--bias cmaes` adds the CMA-ES rollouts "
            "(population 5 x 3 generations on a training motion per 15 designs, the 'designs' stage) and keeps "
            "slightly more episodes, since CMA-ES designs track better.",
            "",
        ]
    for note in dict.fromkeys(r.get("note", "") for r in rows):
        by_threads = {
            r.get("threads"): r
            for r in rows
            if r.get("note", "") == note and r["mode"] == "serial" and not r.get("bias")
        }
        if 1 in by_threads and 2 in by_threads:
            md += [
                f"- 1 -> 2 rollout threads{f' ({note})' if note else ''}: "
                f"{by_threads[2]['episodes_per_s'] / by_threads[1]['episodes_per_s']:.2f}x episodes/s"
            ]
    md += [
        "",
        "On the CPU with more than one thread, a group's tokenization and writes run in a second thread while the next "
        "group rolls out (`tt.generate.generate_shard`), so the stage times overlap and their shares are of "
        "their sum, not of the wall clock.",
        "",
    ]
    if args.full_run is not None:
        md += full_run_section(args.full_run)
    (RESULTS / f"{args.name}.md").write_text("\n".join(md))


def full_run_section(log: Path) -> list[str]:
    """Markdown for a whole-dataset run: the 'RESULT {json}' line its driver script printed."""
    line = [x for x in log.read_text().splitlines() if x.startswith("RESULT ")][-1]
    r = json.loads(line[len("RESULT ") :])
    t, run = r["totals"], r["run"]
    cfg = r.get("command", "")
    return [
        "## A whole dataset",
        "",
        f"`{cfg}`, measured end to end (one run, nothing extrapolated):",
        "",
        "| episodes kept | generated | dropped (< 100 steps) | steps kept | shards | size | wall | kept/s | "
        "CPU [ms] / episode | load avg (mean / max) |",
        "|---|---|---|---|---|---|---|---|---|---|",
        f"| {t['kept']:,} | {t['generated']:,} | {t['dropped'].get('short', 0):,} | {t['steps']:,} | {t['shards']} | "
        f"{t['bytes'] / 2**30:.2f} GiB | {r['wall_s'] / 60:.1f} min | {t['kept'] / r['wall_s']:.1f} | "
        f"{1000 * run['cpu_seconds'] / t['generated']:.2f} | {r['loadavg_mean']:.1f} / {r['loadavg_max']:.1f} |",
        "",
    ]


if __name__ == "__main__":
    main()
