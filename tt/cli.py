"""The ``tt`` command line. Commands import their implementation lazily so ``--help`` is fast."""

from __future__ import annotations

import errno
import json
import logging
import sys
from pathlib import Path
from typing import List, Optional

import typer
from typer.core import TyperGroup

from tt.api import DEFAULT_BUDGET, DEFAULT_CONTROLLER, DEFAULT_METHOD, DEFAULT_REWARD, DEFAULT_SEED, DEFAULT_SPACE

#: Words of library messages that advise loading pickles (torch.load, np.load); tt never passes them on.
_PICKLE_WORDS = ("allow_pickle", "weights_only", "untrusted")


def error_message(e: BaseException) -> str:
    """One line for the user from an exception a command raised.

    tt's errors about bad input (`tt.TTError`) carry their message; file-system errors
    (OSError) name the file; anything else is a bug in tt, said so (`is_bug`).
    """
    if isinstance(e, FileNotFoundError) and e.filename is None and str(e):
        text = str(e)  # tt's own "X does not exist"
    elif isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
        text = f"{e.strerror} while writing {e.filename or 'output'}; free space and run the command again"
    elif isinstance(e, OSError) and e.filename is not None:
        text = f"{e.strerror or type(e).__name__}: {e.filename}"
    elif isinstance(e, MemoryError):
        text = "out of memory; use fewer designs, motions or a smaller batch"
    elif not is_bug(e):
        text = str(e)
    else:
        text = (
            f"internal error ({type(e).__name__}: {e}); this is a bug in tt: please report it with the command "
            "and the traceback above"
        )
    if any(w in text.lower() for w in _PICKLE_WORDS):
        text = "a file holds Python objects (pickled data), which tt never writes and does not load"
    return " ".join(line.strip() for line in text.splitlines() if line.strip())


def is_bug(e: BaseException) -> bool:
    """Whether an exception a command raised is a bug in tt rather than bad input: everything
    but a `tt.TTError` with a message, an OSError (a file, a full disk) and running out of
    memory. A bare ValueError is a bug too: tt raises TTError for every input it refuses."""
    from tt.kernels.errors import TTError

    if isinstance(e, MemoryError):
        return False
    return not (isinstance(e, (TTError, OSError)) and str(e))


#: typer (0.29 on) ships its own copy of click and dispatches through it, so tt imports no
#: `click`: the real package is not a dependency of tt (nor of typer), and its exception
#: classes would never match what typer raises. Usage errors (`typer.BadParameter` and the
#: rest) derive from this class of typer's copy.
_TYPER_CLICK_ERROR = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


class _Commands(TyperGroup):
    """The one error handler of every command: ``error: ...`` on stderr, exit code 2. Bad input
    (`tt.TTError`, a file's OSError) is that one line, its traceback only with ``tt -v``; any
    other exception is a bug in tt, shown with its traceback and a request to report it."""

    def invoke(self, ctx: typer.Context):
        try:
            return super().invoke(ctx)
        except (typer.Exit, typer.Abort, _TYPER_CLICK_ERROR, KeyboardInterrupt):
            raise  # usage errors (a flag out of its range, say) are click's to report
        except Exception as e:
            if ctx.params.get("verbose") or is_bug(e):
                import traceback

                traceback.print_exception(e)
            typer.secho(f"error: {error_message(e)}", fg=typer.colors.RED, err=True)
            raise typer.Exit(code=2) from None


app = typer.Typer(
    cls=_Commands,
    add_completion=False,
    no_args_is_help=True,
    help="tt: motion-conditioned robot co-design (design spaces, batched simulation, RoboTokens, DiT).",
)


#: Help panels of the long commands (`tt optimize`, `tt train`): the common path first, in
#: typer's default "Options" panel, then these.
_MODEL = "Model (learned methods)"
_SEARCH = "Search and rollout"
_ABLATIONS = "Advanced / paper ablations"
_ONLINE = "Online data (--online)"
_RECIPE = "Model and loss"
_SELECTION = "Checkpoint selection"


#: Help of every option that names a reward (`tt.sim.rewards.REWARDS` and `REWARD_ALIASES`).
_REWARD_HELP = (
    "tracking, tracking_torque, tracking_velocity, tracking_size, tracking_weight, or the paper's name "
    "('Tracking Velocity', velocity, ...)."
)


def _reward(value: str | None) -> str | None:
    """Callback of the options that name a reward: the paper's names and the aliases
    (`tt.sim.rewards.reward_name`) become tt's; an unknown name passes through, for the
    command to refuse naming its flag."""
    if value is None:
        return None
    from tt.kernels.errors import TTError
    from tt.sim.rewards import reward_name

    try:
        return reward_name(value)
    except TTError:
        return value


def _fail(message: str) -> None:
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code=2)


def _at_least(flag: str, value: int | float | None, low: int | float) -> None:
    """Refuse a flag below its range (or NaN), naming the flag (not the config field it fills)."""
    if value is not None and not value >= low:
        _fail(f"{flag} must be >= {low}, got {value}")


def _draw_flags(space: str, seed: int, action_noise: float | None) -> None:
    """Refuse, naming the flag, what `tt generate`'s and `tt train --online`'s episode draws
    (`tt.tokens.draws.GenerateConfig`) cannot take."""
    import math

    from tt.sim.designs import get_space

    if seed >= 2**32:
        _fail(f"--seed must be below 2**32 = {2**32}, got {seed}")
    if action_noise is not None and not math.isfinite(action_noise):
        _fail(f"--action-noise must be a finite standard deviation >= 0 [rad or m], got {action_noise}")
    if action_noise and get_space(space).has_contacts:
        _fail(
            f"--action-noise perturbs the commands of tt's Warp rollouts; --space {space} has contacts and rolls out "
            "on MuJoCo C (the mjbatch backend), which runs the clean commands: leave --action-noise out (or give 0)"
        )


def _given(ctx: typer.Context, *names: str) -> list[str]:
    """The flags, among the command's parameters `names`, that the command line gave (a value
    left at its default is not given), in the command's order."""
    flags = []
    for param in ctx.command.params:
        if param.name in names:
            source = ctx.get_parameter_source(param.name)
            if source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP"):
                flags.append(param.opts[0] if param.opts else param.name)
    return flags


def _applies(ctx: typer.Context, names, to: str, chosen: str) -> None:
    """Refuse a flag among parameters `names` the command line gave when it does not apply
    to the chosen method or mode: "FLAG applies to `to`, not `chosen`"."""
    given = _given(ctx, *names)
    if given:
        _fail(f"{given[0]} applies to {to}, not {chosen}")


def _output(path: Path | None, flag: str, *, folder: bool = False) -> None:
    """Create an output's folder before any work (or refuse now), so no result is lost at the end."""
    if path is not None:
        from tt.kernels.files import prepare_output

        prepare_output(path, flag, folder=folder)


def _on_stdout(*outputs: tuple[str, Path | None]) -> bool:
    """Whether one of the (flag, path) outputs goes to stdout (``-``, or ``/dev/stdout``): then
    the command's tables and messages go to stderr, so stdout holds the output alone. Two
    outputs on stdout are refused."""
    from tt.kernels.errors import TTError
    from tt.kernels.files import output_target

    on = []
    for flag, path in outputs:
        if path is None:
            continue
        try:
            if output_target(path, flag)[0] == "stdout":
                on.append(flag)
        except TTError:
            pass  # not writable: `_output` says why
    if len(on) > 1:
        _fail(f"{on[0]} and {on[1]} both write to stdout; give one of them a file name")
    return bool(on)


def _shell(*words) -> str:
    """A command line to print for the user to copy: every word shell-quoted."""
    import shlex

    return " ".join(shlex.quote(str(w)) for w in words)


def _write_json(path: Path, data: dict, flag: str) -> None:
    """Strict JSON (NaN as null, and the file says why); a note when any value was NaN."""
    from tt.kernels.files import write_json

    nulls = write_json(path, data, flag=flag)
    if nulls:
        typer.echo(
            f"note: {path}: {len(nulls)} NaN/inf value(s) written as null (strict JSON has no NaN), "
            f"e.g. {nulls[0]}; the file's null_values entry lists them",
            err=True,
        )


class _Stderr(logging.StreamHandler):
    """Logs to the ``sys.stderr`` of the moment (a test runner swaps it between commands)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


@app.callback()
def _main(
    verbose: bool = typer.Option(
        False, "--verbose", "-v", help="Log at INFO level; on an error, print the traceback too."
    ),
) -> None:
    # tt's warnings (a damaged shard skipped, a checkpoint fallen back from) go to stderr;
    # other libraries' warnings reach it through logging's last-resort handler.
    log = logging.getLogger("tt")
    if not any(isinstance(h, _Stderr) for h in log.handlers):
        handler = _Stderr()
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        log.addHandler(handler)
    log.setLevel(logging.INFO if verbose else logging.WARNING)
    if not verbose:
        # Warp prints its banner and each module load to stdout; the CLI's output is its tables.
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING


@app.command()
def designs(
    space: str = typer.Option("viperx", help="Design space: viperx, aloha, bimanual, quadruped."),
    n: Optional[int] = typer.Option(None, help="Number of designs to sample (default 8)."),
    seed: Optional[int] = typer.Option(None, help="Random seed (default 0)."),
    nominal: bool = typer.Option(
        False, "--nominal", help="Write the space's nominal design (the robot it is built around) instead of sampling."
    ),
    out: Path = typer.Option(Path("designs"), help="Output folder for MJCF files and designs.json."),
) -> None:
    """Sample designs of a space (or take its nominal one); write one MJCF file each and designs.json.

    Over a folder of an earlier `tt designs` run, the MJCF files its designs.json records
    that this run does not rewrite are removed, and the command says so; other files stay,
    and a file this run would overwrite that no earlier run wrote is refused. The set is
    written whole or not at all (a full disk leaves the folder as it was)."""
    from tt.sim.designs import get_space
    from tt.sim.designs.folder import write_design_folder

    if nominal and (n is not None or seed is not None):
        _fail(f"--nominal writes the one nominal design; {'--n' if n is not None else '--seed'} does not apply to it")
    _at_least("--n", n, 1)
    sp = get_space(space)
    ds = [sp.nominal()] if nominal else sp.sample(8 if n is None else n, 0 if seed is None else seed)
    _output(out, "--out", folder=True)
    stale = write_design_folder(ds, out, [sp.to_mjcf(d) for d in ds]).removed
    if stale:
        typer.echo(
            f"removed {len(stale)} design file(s) of an earlier run from {out}/ ({stale[0]} ...); "
            "other files there are left as they were"
        )
    what = f"the nominal {space} design" if nominal else f"{len(ds)} {space} designs"
    typer.echo(f"wrote {what} to {out}/ (designs.json + {len(ds)} MJCF file{'s' if len(ds) > 1 else ''})")


def _motions(names: list[str] | None, files: list[Path] | None, space: str | None = None):
    """Motions from library names (``toss``, ``toss:7``), files, or the validation split."""
    from tt.sim.motions import for_space, load_motion_file, resolve_motion

    motions = [resolve_motion(n) for n in names or []] + [load_motion_file(f) for f in files or []]
    if space is not None:
        motions = for_space(motions, space)
    if not motions:
        _fail("no motion given: use --motion NAME (see `tt motions`) or --motion-file FILE")
    return motions


@app.command()
def motions(
    ctx: typer.Context,
    name: Optional[str] = typer.Option(None, help="Export this motion (NAME or NAME:SEED) instead of listing."),
    out: Optional[Path] = typer.Option(None, help="With --name: write the motion to this .npz file (-: stdout)."),
    arms: Optional[int] = typer.Option(None, help="List only motions for 1 or 2 end effectors."),
    stats: bool = typer.Option(
        False,
        "--stats",
        help="Print each skill's speed, acceleration, extent and orientation range over its train and val motions "
        "(min-max).",
    ),
) -> None:
    """List the motion library, or export one motion to .npz."""
    from rich.console import Console
    from rich.table import Table

    from tt.sim.motions import list_motions, motion_set, motion_stats, resolve_motion, save_npz

    if arms is not None and arms not in (1, 2):
        _fail(f"--arms must be 1 or 2 (end effectors), got {arms}")
    if name is None:
        _applies(ctx, ("out",), "--name (the motion it exports: --name NAME --out FILE.npz)", "the listing")
    else:
        _applies(ctx, ("arms", "stats"), "the listing", "--name, which exports one motion")
    if stats:
        skills = [r.name for r in list_motions(arms=arms)]
        by_skill: dict[str, list] = {s: [] for s in skills}
        for st in motion_stats([m for split in ("train", "val") for m in motion_set(split, arms=arms)]):
            by_skill[st.name.split(":")[0]].append(st)
        cols = (
            ("peak_speed", "peak speed (m/s)"),
            ("p95_speed", "p95 speed (m/s)"),
            ("peak_accel", "peak accel (m/s^2)"),
            ("extent", "extent (m)"),
            ("orn_range", "orn range (deg)"),
            ("duration", "duration (s)"),
        )
        table = Table(title="tt motion library statistics: min-max over each skill's train and val motions")
        for header in ("skill", "motions") + tuple(h for _, h in cols):
            table.add_column(header, justify="left" if header == "skill" else "right")
        for skill, rows in by_skill.items():
            cells = []
            for key, _ in cols:
                v = [getattr(r, key) for r in rows]
                cells.append(f"{min(v):.3g}-{max(v):.3g}")
            table.add_row(skill, str(len(rows)), *cells)
        Console(width=200).print(table)
        return
    if name is None:
        table = Table(title="tt motion library (50 Hz)")
        rows = [r.row() for r in list_motions(arms=arms)]
        for key in ("name", "arms", "duration_s", "train", "val", "summary"):
            table.add_column(key)
        for r in rows:
            table.add_row(*[str(r[k]) for k in ("name", "arms", "duration_s", "train", "val", "summary")])
        Console().print(table)
        return
    if out is None:
        _fail("--name needs --out FILE.npz")
    m = resolve_motion(name)
    _output(out, "--out")
    quiet = _on_stdout(("--out", out))
    save_npz(m, out)
    typer.echo(f"wrote {m.name}: {m.steps} steps, {m.arms} arm(s), {m.duration:.2f} s to {out}", err=quiet)


@app.command()
def validate(
    ctx: typer.Context,
    design: str = typer.Option(..., help="designs.json or designs.json#i."),
    motion: Optional[List[str]] = typer.Option(None, help="Motion name (repeatable); see `tt motions`."),
    motion_file: Optional[List[Path]] = typer.Option(None, help="Motion file .npz / UMI .zarr (repeatable)."),
    reward: str = typer.Option(DEFAULT_REWARD, help=_REWARD_HELP, callback=_reward),
    space: Optional[str] = typer.Option(None, help="Design space; checked against the designs' own."),
    json_out: Optional[Path] = typer.Option(
        None,
        "--json",
        help="Write the metrics and designs to this JSON file (-: stdout, the table then goes to stderr).",
    ),
    episode: Optional[Path] = typer.Option(
        None, help="Also save the rollouts to this episode file (.npz) for `tt view` (-: stdout)."
    ),
    controller: str = typer.Option(
        DEFAULT_CONTROLLER,
        help="ik: the MuJoCo + mink oracle; model: the DiT's control task (its mean command, one network call per "
        "control step, each command the mean of the recent queries' predictions for it: "
        "`tt.dit.policies.ControllerConfig`) on tt's batched Warp physics.",
    ),
    checkpoint: Optional[Path] = typer.Option(
        None,
        help="--controller model: DiT checkpoint file or run folder (default: the space's shipped controller, "
        "<space>_<size>_control.pt, else its shipped checkpoint).",
    ),
    device: Optional[str] = typer.Option(
        None, help="--controller model: Warp/torch device (default: cuda if present, else cpu)."
    ),
    ensemble: Optional[int] = typer.Option(
        None,
        help="--controller model: queries whose predictions each command averages (default: all whose window "
        "holds the step, 7 for the shipped models; 1: the paper's single query); measurements: "
        "docs/results/controller.md.",
    ),
) -> None:
    """Run a controller on designs and motions (the MuJoCo + mink oracle, or the DiT); print the metrics table."""
    from rich.console import Console

    from tt.api import control_checkpoint
    from tt.api import validate as validate_designs
    from tt.report import columns_for, rich_table, summary_row
    from tt.sim.designs import get_space, load_designs

    _output(json_out, "--json")
    _output(episode, "--episode")
    quiet = _on_stdout(("--json", json_out), ("--episode", episode))
    designs = load_designs(design)
    spaces = {d.space for d in designs}
    if space is not None and spaces != {space}:
        _fail(f"--space {space} but the designs are from {sorted(spaces)}")
    sp_name = designs[0].space
    if len(spaces) > 1:
        _fail(f"designs from several spaces in one call: {sorted(spaces)}")
    ms = _motions(motion, motion_file, sp_name)
    if controller not in ("ik", "model"):
        _fail(f"--controller {controller!r} does not exist; controllers: ik, model")
    if controller == "ik":
        _applies(ctx, ("checkpoint", "device", "ensemble"), "--controller model", "--controller ik")
    if controller == "model" and ensemble is not None:
        _at_least("--ensemble", ensemble, 1)
    ckpt = control_checkpoint(sp_name, checkpoint) if controller == "model" else None
    ev = validate_designs(
        designs,
        ms,
        reward,
        controller=controller,
        checkpoint=ckpt,
        device=device,
        ensemble=ensemble,
        progress=controller == "model",
    )
    ep = ev.episode
    title = "oracle (MuJoCo C + mink)" if ckpt is None else f"DiT controller ({ckpt.name}, Warp physics)"
    rows = []
    for i, _ in enumerate(designs):
        rows.append({"name": f"design {i}", **summary_row(ev.metrics, i)})
    if len(designs) > 1:
        rows.append({"name": "mean", **summary_row(ev.metrics)})
    Console(stderr=quiet).print(
        rich_table(rows, columns_for(reward), title=f"{title}, {reward}, motions: {', '.join(m.name for m in ms)}")
    )
    if json_out is not None:
        sp = get_space(sp_name)
        _write_json(
            json_out,
            {
                "reward": reward,
                "controller": controller,
                "motions": [m.name for m in ms],
                "designs": [sp.to_dict(d) for d in designs],
                "metrics": rows,
                "per_motion": {k: v.tolist() for k, v in ev.metrics.items()},
            },
            "--json",
        )
    if episode is not None:
        from tt.viz.episode_file import save_episode_npz

        path = save_episode_npz(
            episode, ev.episode if controller == "ik" else ep, designs, motion_name=", ".join(m.name for m in ms)
        )
        hint = "" if quiet else f"; show them with `{_shell('tt', 'view', path)}`"
        typer.echo(f"wrote {path}: {len(designs) * len(ms)} rollouts{hint}", err=quiet)


@app.command()
def rollout(
    ctx: typer.Context,
    space: str = typer.Option("viperx", help="Design space: viperx, aloha, bimanual, quadruped."),
    n: int = typer.Option(16, help="Random designs of the space (seed --seed); not with --design."),
    seed: int = typer.Option(0, help="Random seed of the designs."),
    design: Optional[str] = typer.Option(None, help="designs.json or designs.json#i instead of random designs."),
    motion: Optional[List[str]] = typer.Option(None, help="Motion name (repeatable; default: toss); see `tt motions`."),
    motion_file: Optional[List[Path]] = typer.Option(None, help="Motion file .npz / UMI .zarr (repeatable)."),
    backend: Optional[str] = typer.Option(
        None, help="warp | mjwarp | newton | mjbatch | mujoco (default: warp; mjbatch for spaces with contacts)."
    ),
    device: Optional[str] = typer.Option(None, help="Warp/torch device (default: cuda if present, else cpu)."),
    reward: str = typer.Option("tracking", help=_REWARD_HELP, callback=_reward),
    out: Optional[Path] = typer.Option(
        None, help="Folder for designs.json, episode.npz (for `tt view`) and summary.json."
    ),
    threads: Optional[int] = typer.Option(
        None,
        "--threads",
        min=1,
        help="CPU threads of warp / mjbatch rollouts (default: every core); results are the same for any count.",
    ),
    graph: Optional[bool] = typer.Option(
        None, "--graph/--no-graph", help="CUDA graphs for the warp / mjwarp launches (default: on a CUDA device)."
    ),
) -> None:
    """Roll out N designs x the motions in one batch (worlds = designs x motions); print the
    metrics per motion and the world-steps per second."""
    import time

    from rich.console import Console

    from tt.baselines.evaluate import evaluate_designs
    from tt.baselines.problem import default_backend
    from tt.report import columns_for, rich_table, summary_row
    from tt.sim.backends import BACKENDS
    from tt.sim.controller import IKConfig
    from tt.sim.designs import get_space, load_designs

    _output(out, "--out", folder=True)
    sp = get_space(space)
    if design is not None:
        _applies(ctx, ("n", "seed"), "random designs", "--design, which reads them from a file")
        designs = load_designs(design)
        spaces = {d.space for d in designs}
        if spaces != {space}:
            _fail(f"--space {space} but the designs of {design} are from {sorted(spaces)}")
    else:
        _at_least("--n", n, 1)
        designs = sp.sample(n, seed)
    ms = _motions(motion if (motion or motion_file) else ["toss"], motion_file, sp.name)
    backend = backend or default_backend(sp.name)
    if backend not in BACKENDS:
        _fail(f"--backend {backend!r} does not exist; backends: {', '.join(BACKENDS)}")
    worlds = len(designs) * len(ms)
    # A world-step is one physics step of one world, counted over each motion's length; every
    # design of a space has the space's timestep (`tt.sim.designs.mjcf.header_xml`).
    world_steps = IKConfig().substeps(sp.model(designs[0])) * len(designs) * sum(mo.steps for mo in ms)
    start = time.perf_counter()
    ev = evaluate_designs(
        designs, ms, reward, backend=backend, device=device, progress=True, threads=threads, graph=graph
    )
    seconds = time.perf_counter() - start
    ep, metrics = ev.episode, ev.metrics
    rows = [{"name": mo.name, **summary_row({k: v[:, j] for k, v in metrics.items()})} for j, mo in enumerate(ms)]
    if len(ms) > 1:
        rows.append({"name": "all", **summary_row(metrics)})
    Console().print(
        rich_table(
            rows,
            columns_for(reward),
            first=("name", "motion"),
            title=f"{len(designs)} {sp.name} designs, backend {backend}, {reward} (mean over designs)",
        )
    )
    rate = world_steps / seconds
    used = None
    if backend in ("warp", "mjbatch") and ep.qpos.device.type == "cpu":
        from tt.kernels.rollout import cpu_threads

        used = cpu_threads(threads)
    typer.echo(
        f"{worlds} worlds, {world_steps:,} world-steps in {seconds:.2f} s: {rate:,.0f} world-steps/s "
        f"(backend {backend}, device {ep.qpos.device}{f', {used} threads' if used else ''}; "
        "model building, kernel compile or cache load and scoring included)"
    )
    if out is not None:
        from tt.sim.designs import save_designs
        from tt.viz.episode_file import save_episode_npz

        save_designs(designs, out / "designs.json")
        save_episode_npz(out / "episode.npz", ep, designs, motion_name=", ".join(mo.name for mo in ms))
        _write_json(
            out / "summary.json",
            {
                "space": sp.name,
                "backend": backend,
                "device": str(ep.qpos.device),
                "reward": reward,
                "motions": [mo.name for mo in ms],
                "designs": len(designs),
                "worlds": worlds,
                "world_steps": world_steps,
                "seconds": seconds,
                "world_steps_per_s": rate,
                "threads": used,
                "metrics": rows,
                "per_world": {k: v.tolist() for k, v in metrics.items()},
            },
            "--out",
        )
        typer.echo(
            f"wrote {out}/designs.json, episode.npz (show with `{_shell('tt', 'view', out / 'episode.npz')}`) "
            "and summary.json"
        )


def _check_critic(path: Path, space: str) -> None:
    """Refuse a --critic-checkpoint that cannot be the dynamics critic of --space's designs,
    each message naming --critic-checkpoint (the sampling model's --checkpoint is another
    file): unreadable, of another space, or not trained on the dynamics task."""
    from tt.dit.checkpoint import load_model

    try:
        critic = load_model(path, device="cpu")
    except (ValueError, OSError) as e:
        _fail(f"--critic-checkpoint: {error_message(e)}")
    if critic.space is not None and critic.space != space:
        _fail(
            f"--critic-checkpoint {path} was trained on design space {critic.space!r}, and --space is {space!r}; "
            f"give a critic trained on {space!r}"
        )
    if not critic.trained_on("dynamics"):
        _fail(
            f"--critic-checkpoint {path} was trained on --task {'+'.join(critic.tasks)}, not the dynamics task a "
            "critic needs (train one with --task dynamics)"
        )


def _validated_rows(designs, motions, reward: str, names: list[str]) -> list[dict]:
    """Oracle re-run of each design on every motion, one summary row per design."""
    from tt.baselines.evaluate import evaluate_designs
    from tt.report import summary_row

    ev = evaluate_designs(designs, motions, reward, backend="mujoco")
    return [{"name": n, **summary_row(ev.metrics, i)} for i, n in enumerate(names)]


@app.command()
def optimize(
    ctx: typer.Context,
    space: str = typer.Option(DEFAULT_SPACE, help="Design space."),
    motion: Optional[List[str]] = typer.Option(None, help="Motion name (repeatable); see `tt motions`."),
    motion_file: Optional[List[Path]] = typer.Option(None, help="Motion file (repeatable)."),
    reward: str = typer.Option(DEFAULT_REWARD, help=_REWARD_HELP, callback=_reward),
    method: str = typer.Option(DEFAULT_METHOD, help="random | cmaes | zeroth | dgs | zeroth-sim | dgs-sim."),
    budget: int = typer.Option(DEFAULT_BUDGET, help="Candidate designs per motion."),
    seed: int = typer.Option(DEFAULT_SEED, help="Random seed."),
    device: Optional[str] = typer.Option(None, help="Warp/torch device (default: cuda if present)."),
    json_out: Optional[Path] = typer.Option(
        None, "--json", help="Write design, time and metrics as JSON (-: stdout, tables to stderr)."
    ),
    checkpoint: Optional[Path] = typer.Option(
        None, help="DiT checkpoint or run folder (default: the shipped one).", rich_help_panel=_MODEL
    ),
    samples: Optional[int] = typer.Option(
        None, help="Candidates to sample (default: --budget).", rich_help_panel=_MODEL
    ),
    num_steps: int = typer.Option(100, help="DDIM steps.", rich_help_panel=_MODEL),
    critic: Optional[str] = typer.Option(
        None, help="How candidates are scored: joint (the paper's) | dynamics.", rich_help_panel=_MODEL
    ),
    critic_checkpoint: Optional[Path] = typer.Option(
        None, help="Checkpoint whose dynamics task scores them (default: the shipped critic).", rich_help_panel=_MODEL
    ),
    refine: int = typer.Option(0, help="Critic-refinement iterations of the winner.", rich_help_panel=_MODEL),
    scale: Optional[float] = typer.Option(
        None, help="dgs: guidance scale (default: the space's).", rich_help_panel=_MODEL
    ),
    verify: Optional[int] = typer.Option(
        None, help="zeroth-sim, dgs-sim: candidates simulated (default: all).", rich_help_panel=_MODEL
    ),
    init: Optional[str] = typer.Option(
        None, help="cmaes: 'model' starts from the model's samples.", rich_help_panel=_MODEL
    ),
    popsize: int = typer.Option(5, help="CMA-ES population size.", rich_help_panel=_SEARCH),
    generations: int = typer.Option(3, help="CMA-ES generations per restart.", rich_help_panel=_SEARCH),
    sequential: bool = typer.Option(
        False, "--sequential", help="CMA-ES one rollout at a time on the oracle.", rich_help_panel=_SEARCH
    ),
    backend: Optional[str] = typer.Option(
        None, help="warp | mjwarp | newton | mjbatch | mujoco (default: per space).", rich_help_panel=_SEARCH
    ),
    threads: Optional[int] = typer.Option(
        None, "--threads", min=1, help="CPU threads of warp / mjbatch rollouts (default: all).", rich_help_panel=_SEARCH
    ),
    critic_samples: int = typer.Option(
        1, help="Dynamics predictions averaged per candidate.", rich_help_panel=_ABLATIONS
    ),
    critic_on: Optional[str] = typer.Option(
        None, help="What the dynamics critic is asked: tokens | designs.", rich_help_panel=_ABLATIONS
    ),
    sim_grad_weight: float = typer.Option(
        0.0, help="dgs: share of the simulator's gradient (0..1).", rich_help_panel=_ABLATIONS
    ),
    guide_by: str = typer.Option("model", help="dgs: model (the paper's) | critic.", rich_help_panel=_ABLATIONS),
    critic_at: str = typer.Option(
        "tokens",
        help="dgs --guide-by critic: tokens | design | project | continuous | start.",
        rich_help_panel=_ABLATIONS,
    ),
) -> None:
    """Optimize a design for motions and a reward; validate the winner on the oracle.

    Methods: random, cmaes (batched, or --sequential on the oracle), zeroth and dgs (the
    diffusion model's Zeroth-Order search and Dynamics Self-Guidance, on the space's shipped
    checkpoint unless --checkpoint), and the hybrids, where the model proposes and the batched
    simulator verifies: zeroth-sim, dgs-sim and cmaes --init model. Each option in full:
    docs/cli.md.
    \f
    The options in detail:

    - `--method`: the hybrids zeroth-sim and dgs-sim simulate `--verify` K of the model's best
      candidates (best predicted first; default: all `--samples`); `--method cmaes --init model`
      is the third hybrid: CMA-ES started from the model's samples (its screen and step sizes)
      instead of random designs.
    - `--backend`: the batched rollout of candidates: warp, mjwarp, newton, mjbatch or mujoco
      (default: warp, or mjbatch for spaces with contacts: quadruped).
    - `--threads`: CPU threads of the warp and mjbatch backends' rollouts (default: every
      core); results are the same for any count.
    - `--sequential`: CMA-ES the paper's way, one rollout at a time on the oracle.
    - `--json`: the design, time and metrics as JSON; `-` is stdout, and the tables then go to
      stderr.
    - `--checkpoint` (learned methods): a DiT checkpoint file or run folder; default: the
      space's shipped one in checkpoints/.
    - `--samples` (learned methods): candidates to sample; default: `--budget`, or with
      `--init model` its screen size.
    - `--critic` (learned methods): how candidates are scored: 'joint' (the paper's: each
      candidate's co-sampled dynamics) or 'dynamics' (the dynamics task's prediction from its
      sampled design; the default for models trained on that task).
    - `--critic-checkpoint` (learned methods): another checkpoint of the same space whose
      dynamics task scores the candidates (e.g. one trained with `--task dynamics` alone);
      implies `--critic dynamics`. Default: the space's shipped dynamics specialist when the
      sampling checkpoint is the shipped one (unless `--critic joint` or `--critic-on tokens`).
    - `--refine` (zeroth, dgs): iterations of critic refinement of the returned design: its
      continuous choices climb the dynamics critic's predicted reward along central
      differences, each design's start re-simulated (tt.guidance.refine; 0: none);
      measurements: docs/results/codesign.md.
    - `--critic-samples` ('dynamics' critic): dynamics predictions averaged per candidate (a
      better ranking for k times the critic's cost).
    - `--critic-on` ('dynamics' critic): what it is asked about: 'tokens' (each candidate's
      sampled embodiment) or 'designs' (the design it decodes to, as tt predict asks; every
      candidate is decoded first). Default: 'designs' for a critic trained with
      `--dynamics-start`, else 'tokens'.
    - `--guide-by` (dgs): what the guidance differentiates: 'model' (the sampling model's own
      predicted dynamics, the paper's) or 'critic' (the dynamics critic's prediction for each
      step's design, tt's scale unless `--scale`).
    - `--critic-at` (dgs `--guide-by critic`): where the critic's gradient is taken: 'tokens'
      (each step's predicted clean tokens), 'design' (the design they decode to), 'project'
      (the decoded design's, and each guided step continues from that design; `--scale` is
      then the RMS token step at full noise), 'continuous' (as 'tokens', moving only the
      continuous attributes of the sampled structure's tokens) or 'start' (as 'tokens', plus
      the gradient through the decoded design's simulated start, which a critic told the start
      otherwise takes as a constant); measurements: docs/experiments.md.
    """
    import numpy as np
    from rich.console import Console

    from tt.baselines import Problem
    from tt.optimizers import LEARNED, METHODS, run_optimizer
    from tt.report import columns_for, rich_table
    from tt.sim.designs import get_space

    methods = [m for m in METHODS if m != "cmaes-init-model"]  # that one is --method cmaes --init model
    if method not in methods:
        _fail(f"--method {method!r} does not exist; methods: {', '.join(methods)}")
    if init not in (None, "model"):
        _fail(f"--init {init!r}: the only initialisation is 'model'")
    if init is not None and method != "cmaes":
        _fail(f"--init model initialises CMA-ES; it does not apply to --method {method}")
    if verify is not None and method not in ("zeroth-sim", "dgs-sim"):
        _fail(f"--verify applies to zeroth-sim and dgs-sim, not --method {method}")
    if init == "model":
        method = "cmaes-init-model"
    _at_least("--budget", budget, 1)
    _at_least("--seed", seed, 0)
    if method in ("cmaes", "cmaes-init-model"):
        _at_least("--popsize", popsize, 2)
        _at_least("--generations", generations, 1)
    if method in LEARNED:
        _at_least("--samples", samples, 1)
        _at_least("--num-steps", num_steps, 1)
        _at_least("--verify", verify, 1)
        from tt.guidance.zeroth import CRITICS

        if critic is not None and critic not in CRITICS:
            _fail(f"--critic {critic!r}: valid are {' and '.join(map(repr, CRITICS))}")
        _at_least("--critic-samples", critic_samples, 1)
        if critic == "joint" and critic_samples > 1:
            _fail(
                f"--critic-samples {critic_samples} needs --critic dynamics: the joint critic scores the one draw "
                "sampled with each design"
            )
        from tt.guidance.zeroth import CRITIC_INPUTS

        if critic_on is not None and critic_on not in CRITIC_INPUTS:
            _fail(f"--critic-on {critic_on!r}: valid are {' and '.join(map(repr, CRITIC_INPUTS))}")
        if critic == "joint" and critic_on == "designs":
            _fail(
                "--critic-on designs asks the dynamics critic about the decoded designs; it does not go with "
                "--critic joint"
            )
        if critic == "joint" and critic_checkpoint is not None:
            _fail("--critic-checkpoint is a dynamics critic; it does not go with --critic joint")
        if critic_checkpoint is not None and not critic_checkpoint.exists():
            _fail(f"--critic-checkpoint {critic_checkpoint} does not exist")
        if critic_checkpoint is not None:
            _check_critic(critic_checkpoint, space)
        if verify is not None and verify > (samples or budget):
            _fail(
                f"--verify {verify} is larger than --samples {samples or budget}: the simulator can only check "
                "sampled candidates"
            )
    _at_least("--refine", refine, 0)
    if refine and method not in ("zeroth", "dgs"):
        _fail(f"--refine refines the design zeroth or dgs returns; it does not apply to --method {method}")
    if refine and critic == "joint":
        _fail("--refine climbs the dynamics critic's prediction; it does not go with --critic joint")
    if not 0.0 <= sim_grad_weight <= 1.0:
        _fail(f"--sim-grad-weight must be in [0, 1], got {sim_grad_weight}")
    from tt.guidance.selfguide import CRITIC_PLACES, GUIDES

    if guide_by not in GUIDES:
        _fail(f"--guide-by {guide_by!r}: valid are {' and '.join(map(repr, GUIDES))}")
    chosen = "--method cmaes --init model" if method == "cmaes-init-model" else f"--method {method}"
    for names, methods in (
        (("checkpoint", "samples", "num_steps", "critic", "critic_samples", "critic_checkpoint", "critic_on"), LEARNED),
        (("popsize", "generations", "sequential"), ("cmaes", "cmaes-init-model")),
        (("scale", "sim_grad_weight", "guide_by"), ("dgs", "dgs-sim")),
    ):
        if method not in methods:
            shown = [("cmaes --init model" if m == "cmaes-init-model" else m) for m in methods]
            _applies(ctx, names, ", ".join(shown[:-1]) + " and " + shown[-1], chosen)
    if guide_by != "model" and method not in ("dgs", "dgs-sim"):
        _fail(f"--guide-by applies to dgs and dgs-sim, not --method {method}")
    if critic_at not in CRITIC_PLACES:
        _fail(f"--critic-at {critic_at!r}: valid are {', '.join(map(repr, CRITIC_PLACES))}")
    if critic_at != "tokens" and guide_by != "critic":
        _fail(f"--critic-at {critic_at} steers by the critic's gradient; it needs --guide-by critic")
    if critic_at == "project" and sim_grad_weight > 0:
        _fail("--critic-at project does not mix in the simulator's gradient (--sim-grad-weight 0)")
    if critic_at == "project" and scale is None:
        _fail("--critic-at project needs --scale: the RMS token step at full noise (e.g. 0.1)")
    _output(json_out, "--json")
    quiet = _on_stdout(("--json", json_out))
    ms = _motions(motion, motion_file, space if _space_ok(space) else None)
    options: dict = {}
    if method in ("cmaes", "cmaes-init-model"):
        options = {"popsize": popsize, "generations": generations, "sequential": sequential}
    if method in LEARNED:
        # checkpoint and critic_checkpoint None: the space's shipped ones (tt.optimizers.learned_defaults)
        options.update(
            checkpoint=checkpoint,
            critic_checkpoint=critic_checkpoint,
            samples=samples,
            num_steps=num_steps,
            critic=critic,
            critic_samples=critic_samples,
        )
        if refine:
            options.update(refine=refine)
        if critic_on is not None:
            options.update(critic_on=critic_on)
        if method in ("dgs", "dgs-sim"):
            options.update(scale=scale, sim_grad_weight=sim_grad_weight, guide_by=guide_by)
            if critic_at != "tokens":
                options.update(CRITIC_PLACES[critic_at])
        if method in ("zeroth-sim", "dgs-sim"):
            options.update(verify=verify)
    problem = Problem(
        space=space,
        motions=tuple(ms),
        reward=reward,
        budget=budget,
        seed=seed,
        backend=backend,
        device=device,
        threads=threads,
    )
    result = run_optimizer(problem, method, **options)  # what tt.optimize runs
    rewards = np.asarray(result.rewards, dtype=np.float64)
    if method in ("random", "cmaes") and rewards.size and not np.any(np.isfinite(rewards) & (rewards != 0.0)):
        # A rollout that terminates at its first step scores exactly 0 under every reward.
        _fail(
            f"no candidate of {rewards.size} survived a single control step (every objective is 0 or NaN): the "
            f"motion is out of reach of these {space} designs; try another motion, space or a larger --budget"
        )
    sp = get_space(space)
    rows = _validated_rows([result.best], ms, reward, [f"{result.method} best"])
    rows[0]["seconds"] = result.seconds
    console = Console(stderr=quiet)
    console.print(
        f"[bold]{result.method}[/bold]: {result.rollouts} rollouts in {result.seconds:.2f} s; best objective "
        f"{result.best_reward:.2f}"
    )
    if "verified_simulated" in result.info:
        info = result.info
        console.print(
            f"verified {info['verified']} of {info['samples']} sampled candidates in the batched simulator: "
            f"predicted vs simulated r = {info['predicted_vs_simulated_r']:.2f}; the simulator's pick was the "
            f"model's #{info['best_predicted_rank'] + 1}"
        )
    if "refine" in result.info:
        r = result.info["refine"]
        if r["steps"][0]:
            console.print(
                f"refined by the dynamics critic: {r['steps'][0]} of at most {r['iterations']} steps taken, its "
                f"objective {r['before'][0]:.2f} -> {r['after'][0]:.2f} (predicted reward "
                f"{r['objective_before']:.2f} -> {result.best_reward:.2f}, same noise) in {r['seconds']:.1f} s"
            )
        else:
            console.print(
                f"refined by the dynamics critic: no step raised its prediction ({r['seconds']:.1f} s); the "
                "sampled design is returned"
            )
    console.print_json(json.dumps(sp.to_dict(result.best)))
    console.print(
        rich_table(
            rows,
            columns_for(reward, [("seconds", "optimize (s)")]),
            title=f"validated on the oracle: {', '.join(m.name for m in ms)}",
        )
    )
    if json_out is not None:
        _write_json(
            json_out,
            {
                "method": result.method,
                "space": space,
                "reward": reward,
                "motions": [m.name for m in ms],
                "budget": budget,
                "seed": seed,
                "backend": problem.backend,
                "optimize_seconds": result.seconds,
                "rollouts": result.rollouts,
                "objective": result.best_reward,
                "design": sp.to_dict(result.best),
                "validated": rows[0],
                "info": result.info,
            },
            "--json",
        )


@app.command()
def predict(
    design: str = typer.Option(..., help="designs.json or designs.json#i."),
    motion: Optional[List[str]] = typer.Option(None, help="Motion name (repeatable); see `tt motions`."),
    motion_file: Optional[List[Path]] = typer.Option(None, help="Motion file .npz / UMI .zarr (repeatable)."),
    checkpoint: Optional[Path] = typer.Option(
        None,
        help="DiT checkpoint file or run folder (default: the designs' space's shipped dynamics specialist, "
        "<space>_<size>_dynamics.pt, else its shipped generalist).",
    ),
    reward: str = typer.Option(DEFAULT_REWARD, help=_REWARD_HELP, callback=_reward),
    samples: int = typer.Option(1, help="Samples per design x motion; their predictions are averaged."),
    num_steps: Optional[int] = typer.Option(
        None,
        help="DDIM steps of the prediction (default: tt.guidance.predicted.CRITIC_DDIM_STEPS, 10 of the 100: "
        "held-out r is flat from 5 to 100, benchmarks/results/dit_ladder_r2c.md).",
    ),
    seed: int = typer.Option(DEFAULT_SEED, help="Seed of the sampling noise."),
    device: Optional[str] = typer.Option(None, help="torch device (default: cuda if present, else cpu)."),
    json_out: Optional[Path] = typer.Option(
        None, "--json", help="Write the predictions to this JSON file (-: stdout, the table then goes to stderr)."
    ),
    via: Optional[str] = typer.Option(
        None,
        help="dynamics: the design as the dynamics task's condition; inpaint: inpainted into the robot task "
        "(default: dynamics when the checkpoint was trained on it).",
    ),
) -> None:
    """The model as a critic: predict each design's dynamics on each motion (its embodiment
    given to the model) and the reward of those dynamics, without simulating."""
    import math

    from rich.console import Console

    from tt.report import columns_for, rich_table
    from tt.sim.designs import DesignError, load_designs

    _at_least("--samples", samples, 1)
    _at_least("--num-steps", num_steps, 1)
    _output(json_out, "--json")
    quiet = _on_stdout(("--json", json_out))
    try:
        designs = load_designs(design)
        spec, _, tail = design.rpartition("#") if "#" in design else (design, "", "")
        indices = list(range(len(designs)))
        if tail:
            i = int(tail)
            indices = [i if i >= 0 else i + len(load_designs(spec))]
    except (DesignError, FileNotFoundError) as e:
        _fail(str(e))
    spaces = sorted({d.space for d in designs})
    if len(spaces) > 1:
        _fail(f"designs from several spaces in one call: {spaces}")
    space = spaces[0]
    ms = _motions(motion, motion_file, space)
    from tt.api import predict as predict_designs
    from tt.api import predict_checkpoint

    ckpt = predict_checkpoint(space, checkpoint)
    pred = predict_designs(
        designs, ms, reward, checkpoint=ckpt, samples=samples, num_steps=num_steps, seed=seed, device=device, via=via
    )

    def clean(v: float) -> float | None:
        return float(v) if math.isfinite(v) else None

    predictions, rows = [], []
    for a, i in enumerate(indices):
        for j, m in enumerate(ms):
            values = {k: clean(float(v[a, j])) for k, v in pred.metrics.items()}
            predictions.append(
                {"design": i, "motion": m.name, "reward": clean(float(pred.reward[a, j])), "metrics": values}
            )
            row = {"name": str(i), "motion": m.name, **{k: v for k, v in values.items() if v is not None}}
            if values.get("survival") is not None:
                row["survival_pct"] = 100.0 * values["survival"]
            rows.append(row)
    Console(stderr=quiet).print(
        rich_table(
            rows,
            [("motion", "motion")] + columns_for(reward),
            first=("name", "design"),
            title=f"predicted by {Path(ckpt).name} ({samples} sample(s), {reward}; not simulated)",
        )
    )
    if json_out is not None:
        _write_json(
            json_out,
            {
                "reward": reward,
                "motions": [m.name for m in ms],
                "space": space,
                "checkpoint": str(ckpt),
                "samples": samples,
                "predictions": predictions,
            },
            "--json",
        )
        typer.echo(f"wrote {len(predictions)} predictions to {json_out}", err=quiet)


@app.command()
def view(
    source: str = typer.Argument(..., help="designs.json[#i] or an episode file episode.npz[#w]."),
    motion: Optional[str] = typer.Option(None, help="Target motion to draw: library name or file."),
    html: Optional[Path] = typer.Option(None, help="Write one self-contained offline HTML file (-: stdout)."),
    serve: bool = typer.Option(False, help="Start a live meshcat server and print its URL."),
    host: Optional[str] = typer.Option(
        None,
        help="--serve: the address the viewer listens on (default 127.0.0.1, this machine only; 0.0.0.0: every "
        "interface).",
    ),
    png: Optional[Path] = typer.Option(None, help="Also screenshot the HTML with headless Chromium (-: stdout)."),
    time: Optional[float] = typer.Option(None, help="Animation time (s) the HTML opens paused at."),
) -> None:
    """Show designs or rollouts in meshcat, live or as standalone HTML."""
    from tt.kernels.files import is_stdout
    from tt.viz.cli import view_cmd

    _output(html, "--html")
    _output(png, "--png")
    quiet = _on_stdout(("--html", html), ("--png", png))
    if png is not None and is_stdout(html):
        _fail("--png renders the HTML file --html writes; give --html a file name, not -")
    view_cmd(
        source,
        motion=motion,
        html=html,
        serve=serve,
        host=host,
        png=png,
        time=time,
        echo=lambda text: typer.echo(text, err=quiet),
    )


@app.command()
def train(
    ctx: typer.Context,
    data: Optional[Path] = typer.Option(None, help="Dataset folder from `tt generate` (or an episode token file)."),
    online: bool = typer.Option(False, "--online", help="Train on episodes simulated as training goes (no --data)."),
    task: str = typer.Option(
        "robot", help="robot | dynamics | control, or several joined by '+'; both = robot+control."
    ),
    size: str = typer.Option("small", help="tiny | mini | small | large."),
    out: Path = typer.Option(Path("runs/dit"), help="Run folder: checkpoints, loss.csv, loss.png."),
    steps: int = typer.Option(10_000, help="Optimizer steps."),
    batch_size: int = typer.Option(64, help="Episodes per batch."),
    lr: Optional[float] = typer.Option(None, help="Peak learning rate (default: the paper's for the size)."),
    device: Optional[str] = typer.Option(None, help="torch device (default: cuda if present, else cpu)."),
    seed: int = typer.Option(0, help="Random seed."),
    checkpoint_every: int = typer.Option(1000, help="Steps between checkpoints."),
    resume: bool = typer.Option(True, help="Continue from the run folder's last checkpoint."),
    init: Optional[Path] = typer.Option(None, help="Start a new run from this checkpoint's weights (fine-tuning)."),
    space: str = typer.Option("viperx", help="Design space (contact-free).", rich_help_panel=_ONLINE),
    online_designs: int = typer.Option(64, help="New designs per refresh.", rich_help_panel=_ONLINE),
    online_motions: int = typer.Option(4, help="Augmented training motions per refresh.", rich_help_panel=_ONLINE),
    refresh_every: int = typer.Option(50, help="Optimizer steps between refreshes.", rich_help_panel=_ONLINE),
    online_buffer: int = typer.Option(4, help="Refreshes whose episodes training draws from.", rich_help_panel=_ONLINE),
    online_absorbing: bool = typer.Option(
        False, "--online-absorbing", help="Keep terminated episodes to the motion's end.", rich_help_panel=_ONLINE
    ),
    online_select: int = typer.Option(
        1, help="Designs screened per kept episode (1: unselected).", rich_help_panel=_ONLINE
    ),
    uniform_share: float = typer.Option(
        0.0, help="--online-select: share of kept episodes drawn uniformly.", rich_help_panel=_ONLINE
    ),
    select_by: str = typer.Option(
        "tracking", help="--online-select: the reward designs are ranked by.", callback=_reward, rich_help_panel=_ONLINE
    ),
    action_noise: Optional[float] = typer.Option(
        None, help="Control perturbation std, rad or m (0: none).", rich_help_panel=_ONLINE
    ),
    select_designs: int = typer.Option(
        0, help="Held-out designs each checkpoint is scored on (0: off).", rich_help_panel=_SELECTION
    ),
    select_motions: int = typer.Option(5, help="--select-designs: validation motions.", rich_help_panel=_SELECTION),
    select_reward: str = typer.Option(
        "tracking",
        help="--select-designs: the reward predicted and simulated.",
        callback=_reward,
        rich_help_panel=_SELECTION,
    ),
    prediction: str = typer.Option(
        "x0", help="What the network predicts: x0 | eps (the paper's) | v.", rich_help_panel=_RECIPE
    ),
    weighting: str = typer.Option(
        "none", help="Noise-level loss weighting: none | min_snr | edm.", rich_help_panel=_RECIPE
    ),
    min_snr_gamma: float = typer.Option(5.0, help="--weighting min_snr: gamma.", rich_help_panel=_RECIPE),
    type_weight: Optional[List[str]] = typer.Option(
        None, help="Loss weight of a token type, TYPE=W (repeatable).", rich_help_panel=_RECIPE
    ),
    robot_diffusion_steps: int = typer.Option(
        100, help="DDIM training steps T of the robot task.", rich_help_panel=_RECIPE
    ),
    control_diffusion_steps: int = typer.Option(
        5, help="DDIM training steps T of the control task.", rich_help_panel=_RECIPE
    ),
    warmup_steps: int = typer.Option(500, help="Learning-rate warm-up steps.", rich_help_panel=_RECIPE),
    time_ids: str = typer.Option(
        "sinusoidal", help="Time-step ID embedding: sinusoidal | learned.", rich_help_panel=_RECIPE
    ),
    bf16_cpu: bool = typer.Option(
        False, "--bf16-cpu", help="Autocast to bfloat16 on the CPU too.", rich_help_panel=_RECIPE
    ),
    future_states: bool = typer.Option(
        True, help="Control task: also diffuse later states.", rich_help_panel=_ABLATIONS
    ),
    anchor_track: bool = typer.Option(
        False, "--anchor-track", help="Track-link poses as residuals from targets.", rich_help_panel=_ABLATIONS
    ),
    anchor_control: str = typer.Option("", help="Commands as residuals: joints | command.", rich_help_panel=_ABLATIONS),
    known_command: bool = typer.Option(
        False, "--known-command", help="Control task: give the last command.", rich_help_panel=_ABLATIONS
    ),
    control_target_offset: int = typer.Option(
        0, help="Control task: targets this many steps later.", rich_help_panel=_ABLATIONS
    ),
    dynamics_start: bool = typer.Option(
        False, "--dynamics-start", help="Dynamics task: condition on the first step.", rich_help_panel=_ABLATIONS
    ),
    drop_type: Optional[List[str]] = typer.Option(
        None, help="A per-step token type left out (repeatable).", rich_help_panel=_ABLATIONS
    ),
) -> None:
    """Train the diffusion transformer on RoboToken episodes: a dataset (--data) or episodes
    simulated as training goes (--online). Each option in full: docs/cli.md.
    \f
    The options in detail:

    - `--task`: robot, dynamics or control, or several joined by '+' (robot+dynamics: a
      generator that is also a critic for tt predict); both = robot+control.
    - `--init`: start a new run from this checkpoint's EMA weights and normaliser
      (fine-tuning).
    - `--online`: train on episodes the batched Warp simulator generates as training goes,
      instead of `--data`. The online options: `--space` is the (contact-free) design space;
      each refresh rolls out `--online-designs` new designs on `--online-motions` augmented
      training motions (every design runs each), every `--refresh-every` optimizer steps, and
      training draws from the last `--online-buffer` refreshes. `--online-absorbing` keeps
      terminated episodes to the motion's end (the terminal state repeated), so the model sees
      designs fail. `--online-select K` screens K designs per kept episode: each motion keeps
      its `--online-designs` best of `--online-designs` x K screened designs
      (tt.tokens.draws.select_episodes), so the generator learns which designs suit a motion
      (1: uniform designs, unselected); `--uniform-share` is the share of each motion's kept
      episodes drawn uniformly from the screen instead of the best (a critic then still sees
      failures), and `--select-by` the reward they are ranked by. `--action-noise`: the control
      perturbation's standard deviation [rad or m] (default: tt generate's,
      tt.tokens.draws.DEFAULT_ACTION_NOISE; 0: none).
    - `--select-designs N`: score every checkpoint on N held-out designs x `--select-motions`
      validation motions (predicted vs simulated `--select-reward`, as tt predict) and keep the
      best as OUT/best.pt (OUT/selection.csv, selection.png); 0: off. Needs `--task` with robot
      or dynamics.
    - `--prediction`: x0 learns what designs do far faster than the paper's eps
      (benchmarks/results/dit_recipe.md).
    - `--type-weight TYPE=W`: e.g. track_link_obs=4.
    - `--time-ids learned`: a lookup table, as checkpoints before the choice.
    - `--bf16-cpu`: CUDA always autocasts to bfloat16; this autocasts on the CPU too.
    - `--no-future-states`: the control task diffuses commands only, not the window's later
      states.
    - `--anchor-track`: predict track-link poses as residuals from their targets (needs
      `--prediction x0`).
    - `--anchor-control`: delta actions: predict commands as residuals from the current joint
      positions (joints) or from the last command (command, needs `--known-command`); needs
      `--prediction x0`.
    - `--known-command`: the control task gives the model the command that led to the current
      state (a servo's setpoint).
    - `--control-target-offset K`: the target poses beside each step's command are those K
      steps later (the reference's conditioning; DiffIK's look-ahead is 2 steps at 50 Hz).
    - `--dynamics-start`: every dynamics window holds the episode's first step, its state and
      command a clean condition; tt predict then simulates each design's first control step and
      tells the model where it starts (benchmarks/results/critic_failures.md).
    - `--drop-type`: dyna_joint_obs, actuator_obs or control left out of the model's sequence;
      a lean critic (`--task dynamics`) trains on a shorter sequence, measured to learn far less
      (benchmarks/results/dit_ladder_r2f.md). Not with the control task.
    """
    from tt.dit.cli import train_cmd

    if online == (data is not None):
        _fail("give exactly one source of training data: --data DATASET or --online")
    if not online:
        _applies(
            ctx,
            (
                "space",
                "online_designs",
                "online_motions",
                "refresh_every",
                "online_buffer",
                "online_absorbing",
                "online_select",
                "uniform_share",
                "select_by",
                "action_noise",
            ),
            "--online training",
            "--data, whose episodes are generated already",
        )
    if not select_designs:
        _applies(
            ctx, ("select_motions", "select_reward"), "--select-designs (checkpoint selection)", "a run without it"
        )
    for flag, value, low in (
        ("--steps", steps, 1),
        ("--batch-size", batch_size, 1),
        ("--checkpoint-every", checkpoint_every, 1),
        ("--online-designs", online_designs, 1),
        ("--online-motions", online_motions, 1),
        ("--refresh-every", refresh_every, 1),
        ("--online-buffer", online_buffer, 1),
        ("--online-select", online_select, 1),
        ("--action-noise", action_noise, 0.0),
        ("--seed", seed, 0),
    ):
        _at_least(flag, value, low)
    if lr is not None and not lr > 0:
        _fail(f"--lr must be > 0, got {lr}")
    if data is not None and not data.exists():
        _fail(f"--data {data} does not exist (a dataset folder from `tt generate`, or an episode token file)")
    weights = {}
    for item in type_weight or []:
        name, eq, value = item.partition("=")
        try:
            weights[name] = float(value)
        except ValueError:
            eq = ""
        if not eq or not name:
            _fail(f"--type-weight {item!r} is not TYPE=WEIGHT (e.g. track_link_obs=4)")
    recipe = dict(
        prediction=prediction,
        weighting=weighting,
        min_snr_gamma=min_snr_gamma,
        type_weights=weights,
        bf16_cpu=bf16_cpu,
        robot_diffusion_steps=robot_diffusion_steps,
        control_diffusion_steps=control_diffusion_steps,
        warmup_steps=warmup_steps,
        anchor_track=anchor_track,
        anchor_control=anchor_control,
        known_command=known_command,
        control_target_offset=control_target_offset,
        dynamics_start=dynamics_start,
        future_states=future_states,
        time_ids=time_ids,
        drop_types=tuple(drop_type or ()),
    )
    _output(out, "--out", folder=True)
    selector = None
    if select_designs:
        _at_least("--select-designs", select_designs, 3)
        _at_least("--select-motions", select_motions, 1)
        from tt.dit.tasks import task_names
        from tt.selection import CheckpointSelector, SelectionConfig
        from tt.sim.rewards import REWARDS, get_reward

        trained_tasks = task_names(task)  # a TTError names --task
        if not {"robot", "dynamics"} & set(trained_tasks):
            _fail(
                "--select-designs scores the model as a critic, which needs --task with robot or dynamics, "
                f"got {task!r}"
            )
        if select_reward not in REWARDS:
            _fail(f"--select-reward {select_reward!r} is not a reward; valid: {list(REWARDS)}")
        reads_actuators = {"act_force", "act_vel"} & set(get_reward(select_reward, space).needs)
        if reads_actuators and "actuator_obs" in (drop_type or ()):
            _fail(
                f"--select-reward {select_reward} reads the predicted actuator observations, which --drop-type "
                "actuator_obs leaves out"
            )
        selector = CheckpointSelector(
            out,
            SelectionConfig(designs=select_designs, motions=select_motions, reward=select_reward, device=device),
            fresh=not resume,
        )
    online_config = None
    if online:
        from tt.dit.online import OnlineConfig

        _draw_flags(space, seed, action_noise)
        extra = {} if action_noise is None else {"action_noise": action_noise}
        online_config = OnlineConfig(
            space=space,
            designs=online_designs,
            motions=online_motions,
            refresh_every=refresh_every,
            buffer=online_buffer,
            seed=seed,
            absorbing=online_absorbing,
            select=online_select,
            uniform_share=uniform_share,
            reward=select_by,
            **extra,
        )
    result = train_cmd(
        data,
        task=task,
        size=size,
        out=out,
        steps=steps,
        batch_size=batch_size,
        lr=lr,
        device=device,
        seed=seed,
        checkpoint_every=checkpoint_every,
        resume=resume,
        init=init,
        online=online_config,
        on_checkpoint=selector,
        on_start_over=selector.start_over if selector is not None else None,
        **recipe,
    )
    import os

    if int(os.environ.get("RANK", "0")) != 0:
        return  # a data-parallel run (torchrun) reports from rank 0
    final = float(result.losses[-1]) if len(result.losses) else float("nan")
    typer.echo(
        f"trained to step {result.step} ({result.parameters:,} parameters); final loss {final:.4f}; "
        f"checkpoint {result.checkpoint}"
    )
    if selector is not None and result.step not in {r.step for r in selector.rows}:
        selector(result.step, result.checkpoint)  # a run killed while scoring its last checkpoint
    if selector is not None and selector.best is not None:
        b = selector.best
        typer.echo(
            f"best checkpoint on {select_designs} held-out designs: step {b.step}, within-motion r {b.within_r:.3f}, "
            f"pooled r {b.pooled_r:.3f}: {selector.best_path}"
        )


@app.command()
def generate(
    space: str = typer.Option(
        "viperx",
        help="Design space: viperx, aloha, bimanual (tt's warp kernels), quadruped (MuJoCo C on every thread, "
        "the mjbatch backend: contacts).",
    ),
    designs: int = typer.Option(..., help="Number of designs N."),
    episodes_per_design: int = typer.Option(10, help="Episodes per design K (augmented training motions)."),
    out: Path = typer.Option(..., help="Dataset folder (zarr v3 store); run the same command again to resume it."),
    device: Optional[str] = typer.Option(None, help="Warp/torch device (default: cuda if present, else cpu)."),
    workers: int = typer.Option(1, help="Shards generated at once: worker processes, or the CPUs of --ray local."),
    bias: Optional[str] = typer.Option(
        None, help="Data biasing: cmaes (CMA-ES, population 5, 3 generations per training motion)."
    ),
    seed: int = typer.Option(0, help="Random seed; every shard derives its draws from (seed, shard index)."),
    ray: Optional[str] = typer.Option(
        None, help="Distribute shards as Ray tasks: a cluster address, or 'local' (pip install 'tt\\[ray]')."
    ),
    designs_per_shard: int = typer.Option(1024, help="Designs per shard: the unit of resume and of distribution."),
    min_steps: int = typer.Option(100, help="Drop episodes shorter than this many control steps (100 = 2 s)."),
    action_noise: Optional[float] = typer.Option(
        None,
        help="Control perturbation: std (rad or m) of Gaussian noise on the executed commands, clean ones logged "
        "(default: tt.tokens.draws.DEFAULT_ACTION_NOISE = 0.01; 0: none).",
    ),
    threads: Optional[int] = typer.Option(
        None,
        "--threads",
        min=1,
        help="CPU threads of each worker's warp rollouts (default: the cores shared out over --workers); the "
        "dataset is the same for any count.",
    ),
    select: int = typer.Option(
        1,
        help="Designs screened per kept episode: each motion of a rollout group keeps the best 1/K of the group's "
        "designs on it (--designs counts the screen), so the data pairs motions with designs chosen for "
        "them. 1: every episode.",
    ),
    uniform_share: float = typer.Option(
        0.0,
        help="--select: share of each motion's kept episodes drawn uniformly from the screen instead of the best "
        "(a critic still sees failures).",
    ),
) -> None:
    """Generate a RoboToken dataset: sample designs, roll out, filter, tokenize, write shards."""
    from tt.generate import BIASES, generate_cmd

    if bias is not None and bias not in BIASES:
        _fail(f"--bias {bias!r} does not exist; biases: {', '.join(BIASES)}")
    _draw_flags(space, seed, action_noise)

    for flag, value, low in (
        ("--designs", designs, 1),
        ("--episodes-per-design", episodes_per_design, 1),
        ("--workers", workers, 1),
        ("--designs-per-shard", designs_per_shard, 1),
        ("--min-steps", min_steps, 1),
        ("--action-noise", action_noise, 0.0),
        ("--seed", seed, 0),
        ("--select", select, 1),
    ):
        _at_least(flag, value, low)
    _output(out, "--out", folder=True)
    typer.echo(
        generate_cmd(
            space,
            designs,
            out,
            episodes_per_design=episodes_per_design,
            device=device,
            workers=workers,
            bias=bias,
            seed=seed,
            ray=ray,
            designs_per_shard=designs_per_shard,
            min_steps=min_steps,
            action_noise=action_noise,
            threads=threads,
            select=select,
            uniform_share=uniform_share,
        )
    )


dataset_app = typer.Typer(no_args_is_help=True, help="Inspect RoboToken datasets written by `tt generate`.")
app.add_typer(dataset_app, name="dataset")


@dataset_app.command("info")
def dataset_info(
    path: Path = typer.Argument(..., help="Dataset folder."),
    plot: Optional[Path] = typer.Option(
        None, help="Also save the histogram of episode rewards as this PNG (-: stdout)."
    ),
    json_out: bool = typer.Option(False, "--json", help="Print JSON instead of text."),
) -> None:
    """Counts, token-type maxima, normalisation statistics and the reward histogram of a dataset."""
    from tt.kernels.files import strict_json
    from tt.tokens.info import dataset_info as summarize
    from tt.tokens.info import info_text
    from tt.viz.plots import save_reward_histogram

    _output(plot, "--plot")
    quiet = _on_stdout(("--plot", plot))
    if quiet and json_out:
        _fail("--json prints to stdout, where --plot - writes the PNG; give --plot a file name")
    info, rewards = summarize(path)
    if plot is not None:
        save_reward_histogram(plot, rewards, title=f"{info['space']} dataset {Path(path).name}")
    if json_out:
        clean, nulls = strict_json(info)  # strict JSON: NaN as null, and said so
        if nulls:
            clean["null_values"] = {"why": "NaN or infinite values, written as null (JSON has no NaN)", "fields": nulls}
        typer.echo(json.dumps(clean, indent=1, allow_nan=False))
        return
    typer.echo(info_text(info, rewards) + (f"\nwrote {plot}" if plot is not None else ""), err=quiet)


@dataset_app.command("verify")
def dataset_verify(path: Path = typer.Argument(..., help="Dataset folder.")) -> None:
    """Check every file of every shard against its manifest (size and CRC-32): the check
    `tt generate` runs before it resumes. Exits non-zero naming each damaged shard."""
    from tt.tokens.store import dataset_verify_cmd

    typer.echo(dataset_verify_cmd(path))


@app.command()
def demo(
    space: str = typer.Option("viperx", help="Design space."),
    motion: Optional[str] = typer.Option(
        None, help="Target motion (library name or file; default: the space's, toss; aloha: bi_fling:100)."
    ),
    reward: Optional[str] = typer.Option(
        None, help=_REWARD_HELP + " Default: the space's, tracking; aloha: tracking_velocity.", callback=_reward
    ),
    original: Optional[bool] = typer.Option(
        None,
        "--original/--no-original",
        help="Validate the space's nominal design beside the winners (default: aloha).",
    ),
    budget: int = typer.Option(64, help="Candidate designs for Random and CMA-ES."),
    samples: int = typer.Option(16, help="Candidates for Zeroth-Order and Self-Guidance."),
    num_steps: int = typer.Option(20, help="DDIM steps of Zeroth-Order and Self-Guidance (of 100)."),
    checkpoint: Optional[Path] = typer.Option(
        None, help="DiT checkpoint file or run folder (default: the space's shipped one)."
    ),
    seed: int = typer.Option(0, help="Random seed."),
    out: Path = typer.Option(Path("tt_demo"), help="Folder for demo.json and demo.html."),
    device: Optional[str] = typer.Option(None, help="Warp/torch device (default: cuda if present, else cpu)."),
) -> None:
    """The main job: co-design a robot for a motion with every method; validate; show the winners.

    Random and batched CMA-ES always run; Zeroth-Order and Dynamics Self-Guidance run when
    the space has a shipped DiT checkpoint (or --checkpoint is given). --space aloha: the
    paper's ALOHA experiment on a fling, the original ALOHA against the optimized designs."""
    from rich.console import Console

    from tt.demo import DemoConfig, run_demo
    from tt.report import columns_for, rich_table

    for flag, value, low in (
        ("--budget", budget, 1),
        ("--samples", samples, 1),
        ("--num-steps", num_steps, 1),
        ("--seed", seed, 0),
    ):
        _at_least(flag, value, low)
    config = DemoConfig(
        space=space,
        motion=motion,
        reward=reward,
        budget=budget,
        samples=samples,
        num_steps=num_steps,
        checkpoint=checkpoint,
        seed=seed,
        out=out,
        device=device,
        original=original,
    )
    _output(out, "--out", folder=True)
    rows = run_demo(config, echo=typer.echo)
    space, motion, reward = config.space, config.motion, config.reward
    extra = [("seconds", "optimize (s)"), ("rollouts", "rollouts")] + (
        [("note", "note")] if any("note" in r for r in rows) else []
    )
    Console().print(
        rich_table(
            rows, columns_for(reward, extra), title=f"{space}, {motion}, {reward}: winners validated on the oracle"
        )
    )


@app.command()
def tokenize(
    path: str = typer.Argument(..., help="MJCF .xml, URDF, or designs.json[#i]."),
    as_json: bool = typer.Option(False, "--json", help="Print the counts as JSON."),
    out: Optional[Path] = typer.Option(None, help="Save the tokens to this .npz file (-: stdout)."),
) -> None:
    """Tokenize robots into RoboTokens; print counts per token type and the MJCF text size."""
    from tt.tokens.cli import tokenize_cmd

    _output(out, "--out")
    quiet = _on_stdout(("--out", out))
    if quiet and as_json:
        _fail("--json prints the counts to stdout, where --out - writes the tokens; give --out a file name")
    typer.echo(tokenize_cmd(path, as_json=as_json, out=None if out is None else str(out)), err=quiet)


@app.command()
def detokenize(
    path: Path = typer.Argument(..., help="Tokens .npz (from `tt tokenize --out`)."),
    out: Path = typer.Option(..., help="Write the robot's MJCF here (-: stdout)."),
    index: int = typer.Option(0, help="Which robot of the file."),
    space: Optional[str] = typer.Option(
        None, help="Also fit the design choices of this space (writes OUT.design.json)."
    ),
    project: bool = typer.Option(
        False, help="With --space: take the nearest design when no choice has these tokens' exact structure."
    ),
) -> None:
    """Turn RoboTokens back into MJCF (and, for tt's spaces, design choices)."""
    from tt.tokens.cli import detokenize_cmd

    if project and space is None:
        _fail("--project applies to --space (fitting a space's design to the tokens); give --space too")
    _output(out, "--out")
    quiet = _on_stdout(("--out", out))
    if quiet and space is not None:
        _fail("--space writes OUT.design.json beside --out's file; give --out a file name, not -")
    typer.echo(detokenize_cmd(str(path), str(out), index=index, space=space, project=project), err=quiet)


def _space_ok(space: str) -> bool:
    from tt.sim.designs import SPACE_NAMES

    return space in SPACE_NAMES


def main() -> None:
    app()


if __name__ == "__main__":
    main()
