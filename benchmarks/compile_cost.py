"""What loop unrolling costs and buys in tt's per-topology kernels: first-call compile time
against stepping speed (issue 53: a first call that compiles kernels should cost far less
than 6 minutes).

tt compiles its fused rollout kernel once per topology (`tt.kernels.rollout.rollout_kernels`),
with Warp's module option ``max_unroll`` from `tt.kernels.model.MODULE_OPTIONS`: every loop
whose trip count is a compile-time constant no larger than it is unrolled. The loops run over
a topology's bodies and dofs (and nested, over pairs of them), so the generated C++ grows
with the robot: a 12-dof ALOHA or a mobile bimanual robot is megabytes of source for clang.

For each space and each ``--unrolls`` value, a child process with its own, initially empty,
Warp kernel cache (``WARP_CACHE_PATH``) sets ``max_unroll`` before any tt kernel is declared,
then, on W designs of the space's most common topology among random draws:

* compile: `wp.load_module` of that topology's rollout module, round 1 only (a fresh cache:
  code generation and clang; later rounds load the cached binary); the size of the generated
  C++ source;
* speed: `tt.kernels.rollout.rollout_tree` on one thread for the whole motion (the space's
  default: the toss, the bimanual fling), best of ``--repeats``; world-steps per second count
  every world's every physics step, as `tt rollout` does;
* the records' checksum (qpos, end-effector poses, alive), to say whether the setting changes
  any number.

Rounds alternate the settings, so load drifts reach all of them alike. ``--cli`` then times
the user's first call, ``tt rollout --space S --n N`` in a fresh cache (every topology of N
random designs), at the shipped setting and at ``--cli-unrolls``.

Usage:
    python benchmarks/compile_cost.py [--spaces viperx aloha bimanual] [--unrolls 64 16 8 4]
        [--worlds 256] [--rounds 3] [--repeats 2] [--cli bimanual] [--out benchmarks/results/compile_cost.md]
"""

# No `from __future__ import annotations`: Warp reads the kernels' annotations as objects.
import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

try:
    from kernel_cost import common_topology_models
    from machine import load_line, machine_header, write_report
except ImportError:  # run as a module from the repository root
    from benchmarks.kernel_cost import common_topology_models
    from benchmarks.machine import load_line, machine_header, write_report


def _child(cfg: dict) -> dict:
    """One (space, max_unroll) measurement in this process (its kernel cache set by the parent)."""
    import numpy as np
    import warp as wp

    wp.config.quiet = True
    import tt.kernels.model as km

    # Before any tt kernel is declared: rollout_kernels reads the dict when it registers a module.
    km.MODULE_OPTIONS["max_unroll"] = cfg["max_unroll"]
    from tt.kernels.model import build_tree_model, topology_of
    from tt.kernels.rollout import motion_arrays, rollout_kernels, rollout_tree
    from tt.sim.controller import IKConfig
    from tt.sim.designs import get_space
    from tt.sim.motions import default_motion, for_space, get_motion

    space = get_space(cfg["space"])
    sites = space.ee_sites()
    models = common_topology_models(space, cfg["worlds"])
    W = len(models)
    topo = topology_of(models[0], sites)
    tree = build_tree_model(models, sites, device="cpu")
    motion = for_space([get_motion(default_motion(space.ee_count))], cfg["space"])[0]
    steps = motion.steps
    marrays = motion_arrays(motion.pos[None], motion.quat[None], [steps], device="cpu")

    kernels = rollout_kernels(topo)
    start = time.perf_counter()
    wp.load_module(kernels.module, device="cpu")
    compile_s = time.perf_counter() - start
    sources = list(Path(wp.config.kernel_cache_dir).rglob(f"*{kernels.module}_*.cpp"))
    source_bytes = sum(p.stat().st_size for p in sources) if sources else None

    config = IKConfig()
    args = config.rollout_args()
    # Untimed first call: it loads the other modules a rollout launches (start posture, noise).
    out = rollout_tree(tree, marrays, W, steps, **args, threads=1, chunk=None, device="cpu")
    best = float("inf")
    for _ in range(cfg["repeats"]):
        start = time.perf_counter()
        out = rollout_tree(tree, marrays, W, steps, **args, threads=1, chunk=None, device="cpu")
        best = min(best, time.perf_counter() - start)
    digest = hashlib.sha256()
    for name in ("qpos", "ee_pos", "ee_quat", "alive"):
        digest.update(np.ascontiguousarray(getattr(out, name).numpy()).tobytes())
    return {
        "space": cfg["space"],
        "max_unroll": cfg["max_unroll"],
        "round": cfg["round"],
        "worlds": W,
        "dofs": topo.dof_count,
        "bodies": topo.body_count,
        "steps": steps,
        "compile_s": compile_s,
        "source_bytes": source_bytes,
        "rollout_s": best,
        "rate": W * steps * config.substeps(models[0]) / best,
        "checksum": digest.hexdigest()[:16],
    }


def _run_child(cfg: dict, cache: str) -> dict:
    env = {**os.environ, "WARP_CACHE_PATH": cache}
    done = subprocess.run(
        [sys.executable, __file__, "--child", json.dumps(cfg)], env=env, capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise RuntimeError(f"child {cfg} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


_CLI_CODE = (
    "import sys, tt.kernels.model as km; km.MODULE_OPTIONS['max_unroll'] = int(sys.argv[1]); "
    "sys.argv = ['tt', *sys.argv[2:]]; from tt.cli import main; main()"
)


def _cli_first_call(space: str, n: int, unroll: int) -> dict:
    """`tt rollout --space S --n N` in a fresh kernel cache at `unroll`: wall seconds."""
    with tempfile.TemporaryDirectory(prefix="tt_cc_cli_") as cache:
        env = {**os.environ, "WARP_CACHE_PATH": cache}
        start = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-c", _CLI_CODE, str(unroll), "rollout", "--space", space, "--n", str(n)],
            env=env,
            capture_output=True,
            text=True,
            check=False,
        )
        seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"tt rollout failed:\n{done.stderr[-3000:]}")
    summary = [line for line in done.stdout.splitlines() if "world-steps/s" in line]
    return {"space": space, "n": n, "max_unroll": unroll, "seconds": seconds, "summary": summary[-1] if summary else ""}


def _report(records: list[dict], cli: list[dict], meta: dict) -> str:
    """The results page; `meta`: command, loads, worlds, rounds, repeats (what the run was told)."""
    from tt.kernels.model import MODULE_OPTIONS

    spaces = list(dict.fromkeys(r["space"] for r in records))
    unrolls = sorted({r["max_unroll"] for r in records}, reverse=True)
    full = unrolls[0] if unrolls else None  # the largest setting unrolls every loop of tt's robots (at most ~20 dofs)
    shipped = MODULE_OPTIONS["max_unroll"]
    lines = [
        "# Loop unrolling in tt's per-topology kernels: first-call compile against stepping speed",
        "",
        machine_header("cpu").rstrip("\n"),
        f"- command: `{meta['command']}`" + (f"; {meta['note']}" if meta.get("note") else ""),
        f"- load average (1, 5, 15 min) at the start: {meta['loads'][0]}; at the end: {meta['loads'][1]}",
        f"- tt's setting today (`tt.kernels.model.MODULE_OPTIONS`): max_unroll {shipped}",
        "",
        f"Per space, {meta['worlds']} random designs of its most common topology (seed 0; fewer where the draws "
        "hold fewer of it) on the space's default motion; per setting a child process with its own kernel cache, "
        f"empty in round 1; {meta['rounds']} rounds alternating the settings. Compile: `wp.load_module` of the "
        "topology's rollout module in round 1 (code generation and clang on one thread). Speed: `rollout_tree` on "
        f"one thread, the whole motion, best of {meta['repeats']} per round, then the best round; world-steps count "
        f"every world's every physics step. Ratios are against max_unroll {full}, which unrolls every loop.",
        "",
        "| space | dofs | worlds | max_unroll | C++ source (MB) | compile (s) | world-steps/s, 1 thread "
        f"| speed x max_unroll {full} | records equal max_unroll {full}'s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for space in spaces:
        rows = [r for r in records if r["space"] == space]
        ref = [r for r in rows if r["max_unroll"] == full]
        ref_rate = max(r["rate"] for r in ref)
        for unroll in unrolls:
            mine = [r for r in rows if r["max_unroll"] == unroll]
            first = min(mine, key=lambda r: r["round"])
            rate = max(r["rate"] for r in mine)
            mb = f"{first['source_bytes'] / 1e6:.2f}" if first["source_bytes"] else "-"
            same = "yes, bit for bit" if {r["checksum"] for r in mine} == {r["checksum"] for r in ref} else "no"
            lines.append(
                f"| {space} | {first['dofs']} | {first['worlds']} | {unroll} | {mb} | {first['compile_s']:.1f} "
                f"| {rate / 1e3:,.1f} k | {rate / ref_rate:.2f}x | {same} |"
            )
    lines += ["", "Every round (world-steps/s, 1 thread):", ""]
    lines.append("| space | max_unroll | " + " | ".join(f"round {i + 1}" for i in range(meta["rounds"])) + " |")
    lines.append("|---|---:|" + "---:|" * meta["rounds"])
    for space in spaces:
        for unroll in unrolls:
            mine = sorted(
                (r for r in records if r["space"] == space and r["max_unroll"] == unroll), key=lambda r: r["round"]
            )
            lines.append(f"| {space} | {unroll} | " + " | ".join(f"{r['rate'] / 1e3:,.1f} k" for r in mine) + " |")
    if cli:
        lines += [
            "",
            "## The user's first call",
            "",
            "`tt rollout --space S --n N` in a fresh kernel cache (every topology of N random designs compiles; "
            "model building, the rollout and scoring included; the CLI's threads), wall seconds, run one after "
            "another:",
            "",
            "| command | max_unroll | first call (s) | its summary line |",
            "|---|---:|---:|---|",
        ]
        for c in cli:
            lines.append(
                f"| `tt rollout --space {c['space']} --n {c['n']}` | {c['max_unroll']} | {c['seconds']:.0f} "
                f"| {c['summary']} |"
            )
    if records and shipped in unrolls and shipped != full:
        lines += ["", f"## Reading: max_unroll {shipped} (tt's setting) against {full}", ""]
        for space in spaces:
            mine = [r for r in records if r["space"] == space and r["max_unroll"] == shipped]
            ref = [r for r in records if r["space"] == space and r["max_unroll"] == full]
            c_mine, c_ref = (min(rs, key=lambda r: r["round"])["compile_s"] for rs in (mine, ref))
            speed = max(r["rate"] for r in mine) / max(r["rate"] for r in ref)
            lines.append(
                f"- {space} ({mine[0]['dofs']} dofs): compile {c_ref:.1f} -> {c_mine:.1f} s ({c_ref / c_mine:.1f}x "
                f"less), stepping {speed:.2f}x, records bit for bit: "
                f"{'yes' if {r['checksum'] for r in mine} == {r['checksum'] for r in ref} else 'no'}"
            )
        for space in dict.fromkeys(c["space"] for c in cli):
            calls = {c["max_unroll"]: c["seconds"] for c in cli if c["space"] == space}
            if shipped in calls and full in calls:
                lines.append(
                    f"- the first `tt rollout --space {space}` call: {calls[full]:.0f} -> {calls[shipped]:.0f} s "
                    f"({calls[full] / calls[shipped]:.1f}x less)"
                )
    lines += ["", "Raw records (one per child; `--from-raw` of this file rewrites the page):", "", "```json"]
    lines += [json.dumps({"meta": meta})] + [json.dumps(r) for r in records + cli]
    lines.append("```")
    return "\n".join(lines) + "\n"


def _read_raw(paths: list[str]) -> tuple[list[dict], list[dict], dict]:
    """Records, first calls and meta from pages' raw blocks (or any files of JSON lines)."""
    records, cli, meta = [], [], {}
    lines = [line for path in paths for line in Path(path).read_text().splitlines()]
    for line in lines:
        if not line.startswith("{"):
            continue
        item = json.loads(line)
        if "meta" in item:
            meta = item["meta"]
        elif "rate" in item:
            records.append(item)
        elif "seconds" in item:
            cli.append(item)
    return records, cli, meta


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--spaces", nargs="+", default=["viperx", "aloha", "bimanual"])
    p.add_argument("--unrolls", nargs="+", type=int, default=[64, 16, 8, 4])
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--cli", nargs="*", default=["bimanual"], help="spaces whose first `tt rollout` call is timed")
    p.add_argument("--cli-n", type=int, default=1024)
    p.add_argument("--cli-unrolls", nargs="*", type=int, default=[64, 8])
    p.add_argument(
        "--from-raw", nargs="+", help="rewrite the page from this file's raw records (a page or a log of them)"
    )
    p.add_argument("--out", default="benchmarks/results/compile_cost.md")
    args = p.parse_args()
    if args.child:
        print(json.dumps(_child(json.loads(args.child))))
        return
    if args.from_raw:
        records, cli, meta = _read_raw(args.from_raw)
        for key in ("worlds", "rounds", "repeats"):
            meta.setdefault(key, getattr(args, key))
        meta.setdefault("command", "python benchmarks/compile_cost.py")
        meta.setdefault("loads", ("-", "-"))
        out = write_report(args.out, _report(records, cli, meta).splitlines())
        print(f"wrote {out}")
        return

    load_start = load_line()
    records = []
    with tempfile.TemporaryDirectory(prefix="tt_cc_") as root:
        for rnd in range(1, args.rounds + 1):
            for space in args.spaces:
                for unroll in args.unrolls:
                    cache = os.path.join(root, f"{space}_{unroll}")
                    cfg = {
                        "space": space,
                        "max_unroll": unroll,
                        "worlds": args.worlds,
                        "repeats": args.repeats,
                        "round": rnd,
                    }
                    records.append(_run_child(cfg, cache))
                    print(json.dumps(records[-1]), file=sys.stderr, flush=True)
    cli = []
    for space in args.cli:
        for unroll in args.cli_unrolls:
            cli.append(_cli_first_call(space, args.cli_n, unroll))
            print(json.dumps(cli[-1]), file=sys.stderr, flush=True)
    meta = {
        "command": "python benchmarks/compile_cost.py " + " ".join(sys.argv[1:]),
        "loads": (load_start, load_line()),
        "worlds": args.worlds,
        "rounds": args.rounds,
        "repeats": args.repeats,
    }
    out = write_report(args.out, _report(records, cli, meta).splitlines())
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
