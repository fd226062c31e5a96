"""The ``tt`` command line. Commands import their implementation lazily so ``--help`` is fast."""

from __future__ import annotations

import errno
import inspect
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


def _reflow(text: str) -> str:
    """A docstring's paragraphs as single lines ('- ' items each their own), up to a ``\\f``
    line (the part after it, which --help does not show, kept): rich help keeps every line
    break of a docstring, so wrapped source lines would break mid-sentence on screen."""
    shown, cut, rest = text.partition("\f")
    paragraphs = []
    for para in shown.strip("\n").split("\n\n"):
        items: list[str] = []
        for line in para.splitlines():
            line = line.strip()
            if line.startswith("- ") or not items:
                items.append(line)
            else:
                items[-1] += " " + line
        paragraphs.append("\n".join(items))
    return "\n\n".join(paragraphs) + ("\n\n" + cut + rest if cut else "")


class _Commands(TyperGroup):
    """The one error handler of every command: ``error: ...`` on stderr, exit code 2. Bad input
    (`tt.TTError`, a file's OSError) is that one line, its traceback only with ``tt -v``; any
    other exception is a bug in tt, shown with its traceback and a request to report it."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        for command in [
            *self.commands.values(),
            *(c for g in self.commands.values() for c in getattr(g, "commands", {}).values()),
        ]:
            if command.help:
                command.help = _reflow(inspect.cleandoc(command.help))

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


def _fields(cls, exclude: tuple[str, ...] = ()) -> dict[str, str]:
    """A config dataclass's fields (name -> type annotation text), those in `exclude` left out:
    the keys `_config` accepts."""
    import dataclasses

    return {f.name: str(f.type) for f in dataclasses.fields(cls) if f.name not in exclude}


def _type_ok(value, annotation: str) -> bool:
    """Whether a config value read from TOML / JSON has the type its field's annotation names
    (int, float, str, bool, tuple / list, dict, None); anything else (a config object) is the
    config's own to check."""
    kinds = {
        "bool": bool,
        "int": int,
        "float": (int, float),
        "str": str,
        "tuple": (list, tuple),
        "list": (list, tuple),
        "dict": dict,
        "Mapping": dict,
    }
    words = [w.strip() for w in annotation.replace("|", " ").replace("[", " ").split()]
    named = [kinds[w.split("[")[0]] for w in words if w.split("[")[0] in kinds]
    if not named:
        return True
    if value is None:
        return "None" in words
    if isinstance(value, bool):
        return bool in named
    return any(isinstance(value, k) for k in named)


def _config(items: list[str] | None, keys: dict, flag: str) -> dict:
    """The settings of a repeatable config option: each item a TOML or JSON file, or
    KEY=VALUE (VALUE read as a TOML value, a bare word as a string; ``table.KEY=VALUE`` for a
    table's key); later items override earlier ones, key by key. keys: name -> type annotation
    text, or -> a dict of such for a table. An unknown key, or a value of the wrong type, is
    refused naming the key, the item and the valid keys; the configs check the values."""
    import tomllib

    from tt.kernels.errors import TTError

    out: dict = {}
    for item in items or []:
        name, eq, text = item.partition("=")
        if eq and not Path(item).exists():
            try:
                value = tomllib.loads(f"v = {text}")["v"]
            except tomllib.TOMLDecodeError:
                value = text
            table, dot, key = name.strip().rpartition(".")
            loaded = {table: {key: value}} if dot else {name.strip(): value}
            where = f"{flag} {item}"
        else:
            path = Path(item)
            if not path.is_file():
                raise TTError(f"{flag} {item}: no such file, and not KEY=VALUE (a TOML or JSON file, or KEY=VALUE)")
            try:
                loaded = json.loads(path.read_text()) if path.suffix == ".json" else tomllib.loads(path.read_text())
            except (ValueError, UnicodeDecodeError) as e:
                raise TTError(f"{flag} {item}: not a valid {'JSON' if path.suffix == '.json' else 'TOML'} file ({e})")
            if not isinstance(loaded, dict):
                raise TTError(f"{flag} {item}: holds {type(loaded).__name__}, not a table of settings")
            where = f"{flag} {item}"
        for key, value in loaded.items():
            if key not in keys:
                raise TTError(f"{where}: unknown key {key!r}; valid keys: {', '.join(keys) or 'none'}")
            if isinstance(keys[key], dict):
                if not isinstance(value, dict):
                    raise TTError(f"{where}: {key} is a table ([{key}] or {key}.KEY=VALUE), got {value!r}")
                for sub, v in value.items():
                    if sub not in keys[key]:
                        raise TTError(
                            f"{where}: unknown key {key}.{sub}; valid keys of [{key}]: {', '.join(keys[key])}"
                        )
                    if not _type_ok(v, keys[key][sub]):
                        raise TTError(f"{where}: {key}.{sub} = {v!r} is not of type {keys[key][sub]}")
                out[key] = {**out.get(key, {}), **value}
            else:
                if not _type_ok(value, keys[key]):
                    raise TTError(f"{where}: {key} = {value!r} is not of type {keys[key]}")
                out[key] = tuple(value) if isinstance(value, list) else value
    return out


def _output(path: Path | None, flag: str, *, folder: bool = False) -> None:
    """Create an output's folder before any work (or refuse now), so no result is lost at the end."""
    if path is not None:
        from tt.kernels.files import prepare_output

        prepare_output(path, flag, folder=folder)


def _console(stderr: bool = False, width: int | None = None):
    """A rich console for tables. Piped or redirected (``| tee log``), rich would lay tables out
    in 80 columns and fold every cell; there it takes 200 unless ``COLUMNS`` says otherwise."""
    import os

    from rich.console import Console

    console = Console(stderr=stderr, width=width)
    if width is None and not console.is_terminal and "COLUMNS" not in os.environ:
        console.width = 200
    return console


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


#: Help of every option that names motions.
_MOTION_HELP = "Motion: a library name (toss, toss:7; see `tt motions`) or a .npz / UMI .zarr file (repeatable)."
#: The same, for the commands that run the space's default motion when none is given.
_MOTION_HELP_DEFAULT = _MOTION_HELP[:-1] + "; default: toss, or bi_fling for two-arm spaces."


def _motions(names: list[str] | None, space: str | None = None, default: bool = False):
    """Motions from library names (``toss``, ``toss:7``) or files (a value naming an existing
    path, or ending in .npz or .zarr), placed for `space`; with `default` and no names, the
    space's default motion (`tt.api`'s, the one the Python API runs)."""
    from tt.sim.motions import for_space, load_motion_file, resolve_motion

    if default and not names and space is not None:
        from tt.api import _default_motion

        names = [_default_motion(space)]
    motions = [load_motion_file(n) if _is_motion_file(n) else resolve_motion(n) for n in names or []]
    if space is not None:
        motions = for_space(motions, space)
    if not motions:
        _fail("no motion given: use --motion NAME (see `tt motions`) or --motion FILE.npz")
    return motions


def _is_motion_file(value: str) -> bool:
    """Whether a --motion value names a file rather than a library motion."""
    return value.endswith((".npz", ".zarr", ".zarr/")) or Path(value).exists()


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
        _console(width=200).print(table)
        return
    if name is None:
        table = Table(title="tt motion library (50 Hz)")
        rows = [r.row() for r in list_motions(arms=arms)]
        for key in ("name", "arms", "duration_s", "train", "val", "summary"):
            table.add_column(key)
        for r in rows:
            table.add_row(*[str(r[k]) for k in ("name", "arms", "duration_s", "train", "val", "summary")])
        _console().print(table)
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
    design: str = typer.Option(..., help="designs.json or designs.json#i."),
    motion: Optional[List[str]] = typer.Option(None, help=_MOTION_HELP_DEFAULT),
    reward: str = typer.Option(DEFAULT_REWARD, help=_REWARD_HELP, callback=_reward),
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
        help="ik: the MuJoCo + mink oracle; model: the DiT's control task on tt's batched Warp physics (the "
        "space's shipped controller), or a DiT checkpoint file or run folder to use as that controller.",
    ),
    device: Optional[str] = typer.Option(
        None, help="The model controller's Warp/torch device (default: cuda if present, else cpu)."
    ),
) -> None:
    """Run a controller on designs and motions (the MuJoCo + mink oracle, or the DiT); print the metrics table.

    The model controller (`tt.dit.policies.ControllerConfig`): the DiT's mean command, one
    network call per control step, each command the mean of the recent queries' predictions
    for it (docs/results/controller.md); its default checkpoint is the space's shipped
    controller, <space>_<size>_control.pt, else its shipped checkpoint."""
    from tt.api import control_checkpoint
    from tt.api import validate as validate_designs
    from tt.report import columns_for, rich_table, summary_row
    from tt.sim.designs import get_space, load_designs

    _output(json_out, "--json")
    _output(episode, "--episode")
    quiet = _on_stdout(("--json", json_out), ("--episode", episode))
    designs = load_designs(design)
    spaces = {d.space for d in designs}
    sp_name = designs[0].space
    if len(spaces) > 1:
        _fail(f"designs from several spaces in one call: {sorted(spaces)}")
    ms = _motions(motion, sp_name, default=True)
    if controller == "ik":
        if device is not None:
            _fail("--device applies to the model controller, not --controller ik (the oracle runs MuJoCo C)")
        ckpt = None
    else:
        if controller != "model" and not Path(controller).exists():
            _fail(f"--controller {controller!r}: give ik, model, or a DiT checkpoint file or run folder that exists")
        ckpt = control_checkpoint(sp_name, None if controller == "model" else Path(controller))
        controller = "model"
    ev = validate_designs(
        designs,
        ms,
        reward,
        controller=controller,
        checkpoint=ckpt,
        device=device,
        progress=controller == "model",
    )
    ep = ev.episode
    title = "oracle (MuJoCo C + mink)" if ckpt is None else f"DiT controller ({ckpt.name}, Warp physics)"
    rows = []
    for i, _ in enumerate(designs):
        rows.append({"name": f"design {i}", **summary_row(ev.metrics, i)})
    if len(designs) > 1:
        rows.append({"name": "mean", **summary_row(ev.metrics)})
    _console(stderr=quiet).print(
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
    space: str = typer.Option(
        "viperx", help="Design space: viperx, aloha, bimanual, quadruped (with --design: the file's)."
    ),
    n: int = typer.Option(16, help="Random designs of the space (seed --seed); not with --design."),
    seed: int = typer.Option(0, help="Random seed of the designs."),
    design: Optional[str] = typer.Option(None, help="designs.json or designs.json#i instead of random designs."),
    motion: Optional[List[str]] = typer.Option(None, help=_MOTION_HELP_DEFAULT),
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
) -> None:
    """Roll out N designs x the motions in one batch (worlds = designs x motions); print the
    metrics per motion and the world-steps per second."""
    import time

    from tt.baselines.evaluate import evaluate_designs
    from tt.baselines.problem import default_backend
    from tt.report import columns_for, rich_table, summary_row
    from tt.sim.backends import BACKENDS
    from tt.sim.controller import IKConfig
    from tt.sim.designs import get_space, load_designs

    _output(out, "--out", folder=True)
    if design is not None:
        _applies(ctx, ("n", "seed"), "random designs", "--design, which reads them from a file")
        designs = load_designs(design)
        spaces = {d.space for d in designs}
        if not _given(ctx, "space") and len(spaces) == 1:
            space = designs[0].space  # the file's, as validate and predict take it
        if spaces != {space}:
            _fail(f"--space {space} but the designs of {design} are from {sorted(spaces)}")
    sp = get_space(space)
    if design is None:
        _at_least("--n", n, 1)
        designs = sp.sample(n, seed)
    ms = _motions(motion, sp.name, default=True)
    backend = backend or default_backend(sp.name)
    if backend not in BACKENDS:
        _fail(f"--backend {backend!r} does not exist; backends: {', '.join(BACKENDS)}")
    worlds = len(designs) * len(ms)
    # A world-step is one physics step of one world, counted over each motion's length; every
    # design of a space has the space's timestep (`tt.sim.designs.mjcf.header_xml`).
    world_steps = IKConfig().substeps(sp.model(designs[0])) * len(designs) * sum(mo.steps for mo in ms)
    start = time.perf_counter()
    ev = evaluate_designs(designs, ms, reward, backend=backend, device=device, progress=True, threads=threads)
    seconds = time.perf_counter() - start
    ep, metrics = ev.episode, ev.metrics
    rows = [{"name": mo.name, **summary_row({k: v[:, j] for k, v in metrics.items()})} for j, mo in enumerate(ms)]
    if len(ms) > 1:
        rows.append({"name": "all", **summary_row(metrics)})
    _console().print(
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
        f"{worlds} world{'s' if worlds != 1 else ''}, {world_steps:,} world-steps in {seconds:.2f} s: "
        f"{rate:,.0f} world-steps/s "
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


def _validated_rows(designs, motions, reward: str, names: list[str]) -> list[dict]:
    """Oracle re-run of each design on every motion, one summary row per design."""
    from tt.baselines.evaluate import evaluate_designs
    from tt.report import summary_row

    ev = evaluate_designs(designs, motions, reward, backend="mujoco")
    return [{"name": n, **summary_row(ev.metrics, i)} for i, n in enumerate(names)]


@app.command()
def optimize(
    space: str = typer.Option(DEFAULT_SPACE, help="Design space."),
    motion: Optional[List[str]] = typer.Option(None, help=_MOTION_HELP),
    reward: str = typer.Option(DEFAULT_REWARD, help=_REWARD_HELP, callback=_reward),
    method: str = typer.Option(
        DEFAULT_METHOD, help="random | cmaes | zeroth | dgs | zeroth-sim | dgs-sim | cmaes-init-model."
    ),
    budget: int = typer.Option(DEFAULT_BUDGET, help="Candidate designs per motion (the model's samples too)."),
    seed: int = typer.Option(DEFAULT_SEED, help="Random seed."),
    device: Optional[str] = typer.Option(None, help="Warp/torch device (default: cuda if present)."),
    json_out: Optional[Path] = typer.Option(
        None, "--json", help="Write design, time and metrics as JSON (-: stdout, tables to stderr)."
    ),
    checkpoint: Optional[Path] = typer.Option(
        None, help="DiT checkpoint or run folder (default: the shipped one).", rich_help_panel=_MODEL
    ),
    num_steps: int = typer.Option(100, help="DDIM steps.", rich_help_panel=_MODEL),
    refine: int = typer.Option(0, help="Critic-refinement iterations of the winner.", rich_help_panel=_MODEL),
    backend: Optional[str] = typer.Option(
        None, help="warp | mjwarp | newton | mjbatch | mujoco (default: per space).", rich_help_panel=_SEARCH
    ),
    threads: Optional[int] = typer.Option(
        None, "--threads", min=1, help="CPU threads of warp / mjbatch rollouts (default: all).", rich_help_panel=_SEARCH
    ),
    config: Optional[List[str]] = typer.Option(
        None,
        "--config",
        help="The method's settings: KEY=VALUE or a TOML / JSON file (repeatable), e.g. popsize=8, critic=joint.",
        rich_help_panel=_ABLATIONS,
    ),
) -> None:
    """Optimize a design for motions and a reward; validate the winner on the oracle.

    Methods: random, cmaes (batched), zeroth and dgs (the diffusion model's Zeroth-Order search
    and Dynamics Self-Guidance, on the space's shipped checkpoint unless --checkpoint), and the
    hybrids, where the model proposes and the batched simulator verifies: zeroth-sim, dgs-sim
    and cmaes-init-model. Each option in full: docs/cli.md.

    \f
    The options in detail:

    - `--method`: the hybrids zeroth-sim and dgs-sim simulate the model's best candidates
      (best predicted first; `verify=K` of them, default all); cmaes-init-model is CMA-ES
      started from the model's samples (its screen and step sizes) instead of random designs.
    - `--budget`: candidate designs per motion; the learned methods sample as many (unless
      `samples=`), cmaes-init-model screens its samples within it.
    - `--backend`: the batched rollout of candidates: warp, mjwarp, newton, mjbatch or mujoco
      (default: warp, or mjbatch for spaces with contacts: quadruped).
    - `--threads`: CPU threads of the warp and mjbatch backends' rollouts (default: every
      core); results are the same for any count.
    - `--json`: the design, time and metrics as JSON; `-` is stdout, and the tables then go to
      stderr.
    - `--checkpoint` (learned methods): a DiT checkpoint file or run folder; default: the
      space's shipped generator in checkpoints/, its samples ranked by the space's shipped
      dynamics critic.
    - `--refine` (zeroth, dgs): iterations of critic refinement of the returned design: its
      continuous choices climb the dynamics critic's predicted reward along central
      differences, each design's start re-simulated (tt.guidance.refine; 0: none);
      measurements: docs/results/codesign.md.
    - `--config` (the method's settings, what `tt.optimize(..., **options)` takes; each
      method's config validates them, and an unknown key is refused naming the valid ones):
      cmaes (`tt.baselines.CMAESConfig`): `popsize` (5), `generations` per restart (3),
      `sigma0`, `screen`, `sequential=true` (the paper's way: one rollout at a time on the
      oracle). Learned methods (`tt.guidance.zeroth.SamplerConfig`): `samples`, `eta`,
      `critic` ("joint", the paper's: each candidate's co-sampled dynamics; "dynamics": the
      dynamics task's prediction for its design), `critic_checkpoint` (another checkpoint
      of the space whose dynamics task scores the candidates; default: the shipped critic
      beside the shipped generator), `critic_samples`, `critic_on`. dgs, dgs-sim
      (`tt.guidance.selfguide.DGSConfig`): `scale` (default: the space's), `guide_by`
      ("model", the paper's: the sampling model's own predicted dynamics; "critic": the
      dynamics critic's prediction for each step's predicted clean tokens, tt's scale;
      default: "critic" for a generator trained without dynamics when a critic ships or is
      given, else "model"),
      `sim_grad_weight` (share of the simulator's gradient, 0..1; the paper's ablation),
      `sim_grad_start`. zeroth-sim, dgs-sim: `verify` (candidates simulated; default all).
      Measurements of each: docs/results/codesign.md, docs/experiments.md.
    """
    import numpy as np

    from tt.baselines import Problem
    from tt.optimizers import LEARNED, METHODS, method_keys, run_optimizer
    from tt.report import columns_for, rich_table
    from tt.sim.designs import get_space

    if method not in METHODS:
        _fail(f"--method {method!r} does not exist; methods: {', '.join(METHODS)}")
    keys = {k: v for k, v in method_keys(method).items() if k not in ("checkpoint", "num_steps", "refine")}
    options = _config(config, keys, "--config")
    _at_least("--budget", budget, 1)
    _at_least("--seed", seed, 0)
    _at_least("--refine", refine, 0)
    if method in LEARNED:
        options.update(checkpoint=checkpoint, num_steps=num_steps)
        if refine:
            options.update(refine=refine)
    elif checkpoint is not None or refine or num_steps != 100:
        flag = "--checkpoint" if checkpoint is not None else "--refine" if refine else "--num-steps"
        _fail(f"{flag} applies to the learned methods ({', '.join(LEARNED)}), not --method {method}")
    _output(json_out, "--json")
    quiet = _on_stdout(("--json", json_out))
    ms = _motions(motion, space if _space_ok(space) else None)
    problem = Problem(
        space=space,
        motions=tuple(ms),
        reward=reward,
        budget=budget,
        seed=seed,
        backend=backend,
        device=device,
        threads=threads,
        progress=True,
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
    console = _console(stderr=quiet)
    # With no rollout the objective is the critic's prediction, which the oracle's table below checks.
    objective = "best objective" if result.rollouts else "best predicted objective (not simulated)"
    console.print(
        f"[bold]{result.method}[/bold]: {result.rollouts} rollouts in {result.seconds:.2f} s; {objective} "
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
    motion: Optional[List[str]] = typer.Option(None, help=_MOTION_HELP_DEFAULT),
    checkpoint: Optional[Path] = typer.Option(
        None,
        help="DiT checkpoint file or run folder (default: the designs' space's shipped dynamics specialist, "
        "<space>_<size>_dynamics.pt, else its shipped generalist).",
    ),
    reward: str = typer.Option(DEFAULT_REWARD, help=_REWARD_HELP, callback=_reward),
    samples: int = typer.Option(1, help="Samples per design x motion; their predictions are averaged."),
    seed: int = typer.Option(DEFAULT_SEED, help="Seed of the sampling noise."),
    device: Optional[str] = typer.Option(None, help="torch device (default: cuda if present, else cpu)."),
    json_out: Optional[Path] = typer.Option(
        None, "--json", help="Write the predictions to this JSON file (-: stdout, the table then goes to stderr)."
    ),
) -> None:
    """The model as a critic: predict each design's dynamics on each motion (its embodiment
    given to the model) and the reward of those dynamics, without simulating."""
    import math

    from tt.report import columns_for, rich_table
    from tt.sim.designs import DesignError, load_designs
    from tt.sim.rewards import PERCENT_METRICS

    _at_least("--samples", samples, 1)
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
    ms = _motions(motion, space, default=True)
    from tt.api import predict as predict_designs
    from tt.api import predict_checkpoint

    ckpt = predict_checkpoint(space, checkpoint)
    pred = predict_designs(designs, ms, reward, checkpoint=ckpt, samples=samples, seed=seed, device=device)

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
            for key, pct in PERCENT_METRICS.items():  # shares, shown in percent as validate shows them
                if values.get(key) is not None:
                    row[pct] = 100.0 * values[key]
            rows.append(row)
    _console(stderr=quiet).print(
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
    data: Optional[Path] = typer.Option(None, help="Dataset folder from `tt generate` (or an episode token file)."),
    online: bool = typer.Option(
        False,
        "--online",
        help="Train on episodes simulated as training goes (no --data; settings: --config's \\[online]).",
    ),
    space: Optional[str] = typer.Option(
        None, help="Design space of --online's episodes (online.space; default viperx); a dataset has its own."
    ),
    task: Optional[str] = typer.Option(
        None, help="robot | dynamics | control, or several joined by '+'; both = robot+control (default robot)."
    ),
    size: Optional[str] = typer.Option(None, help="tiny | mini | small | large (default small; --init: its own)."),
    out: Path = typer.Option(Path("runs/dit"), help="Run folder: checkpoints, loss.csv, loss.png."),
    steps: Optional[int] = typer.Option(None, help="Optimizer steps (default 10,000)."),
    batch_size: Optional[int] = typer.Option(None, help="Episodes per batch (default 64)."),
    device: Optional[str] = typer.Option(None, help="torch device (default: cuda if present, else cpu)."),
    seed: Optional[int] = typer.Option(None, help="Random seed (default 0)."),
    resume: bool = typer.Option(True, help="Continue from the run folder's last checkpoint."),
    init: Optional[Path] = typer.Option(
        None, help="Start a new run from this checkpoint's weights and layout (fine-tuning)."
    ),
    config: Optional[List[str]] = typer.Option(
        None,
        "--config",
        help="Training settings: a TOML / JSON file (checkpoints/recipes/) or KEY=VALUE (repeatable).",
    ),
) -> None:
    """Train the diffusion transformer on RoboToken episodes: a dataset (--data) or episodes
    simulated as training goes (--online). Each option in full: docs/cli.md.

    \f
    The options in detail:

    - `--task`: robot, dynamics or control, or several joined by '+' (robot+dynamics: a
      generator that is also a critic for tt predict); both = robot+control.
    - `--init`: start a new run from this checkpoint's EMA weights and normaliser
      (fine-tuning). The run takes the checkpoint's network and token layout (size, prediction,
      time IDs, anchors, known command, future states, dynamics start, diffusion steps), so a
      recipe need not repeat them; a setting given in `--config` or as a flag still wins.
    - `--config`: the research settings, from TOML or JSON files (the shipped checkpoints'
      recipes are in checkpoints/recipes/) or `KEY=VALUE` items (VALUE read as TOML: `8`,
      `5e-4`, `true`, `"x0"`, `{track_link_obs = 4}`; a bare word is a string), later items
      winning and flags winning over all. Keys: every field of `tt.dit.train.TrainConfig`
      (prediction, weighting, min_snr_gamma, type_weights, warmup_steps, lr,
      checkpoint_every, robot_diffusion_steps, control_diffusion_steps, time_ids, bf16_cpu,
      future_states, anchor_track, anchor_control, known_command, control_target_offset,
      dynamics_start, ...); the table `[online]` (`online.KEY=VALUE`) of
      `tt.dit.online.OnlineConfig` (space, designs, motions, refresh_every, buffer, absorbing,
      select, uniform_share, reward, action_noise, ...), which also turns on online training;
      and the table `[selection]` of `tt.selection.SelectionConfig` (designs, motions,
      reward): score every checkpoint on `designs` held-out designs x `motions` validation
      motions (predicted vs simulated reward, as tt predict) and keep the best as
      OUT/best.pt (OUT/selection.csv, selection.png); needs a task with robot or dynamics. An
      unknown key is refused naming the valid ones; each config validates its own values.
    - Online training (`--online` or an `[online]` table): each refresh rolls out `designs`
      new designs of `space` (`--space`; the quadruped on mjbatch, the others on tt's
      kernels) on `motions` augmented training motions, every
      `refresh_every` optimizer steps, and training draws from the last `buffer` refreshes;
      `absorbing` keeps terminated episodes to the motion's end; `select K` screens K designs
      per kept episode (each motion keeps its best, tt.tokens.draws.select_episodes; 1:
      uniform designs), `uniform_share` of them drawn uniformly instead, ranked by `reward`;
      `propose N` adds N designs per motion that the generator `proposer` samples for it
      (`propose_steps` DDIM steps) to the screen: iterated self-improvement.
    """
    from tt.dit.cli import train_cmd

    flags = {"task": task, "size": size, "steps": steps, "batch_size": batch_size, "seed": seed}
    settings = train_settings(config, init, **flags)
    online_table = settings.pop("online", None)
    selection = settings.pop("selection", None)
    if space is not None:
        if not online and online_table is None:
            _fail("--space picks the design space of online training: add --online (a dataset has its own space)")
        online_table = {**(online_table or {}), "space": space}  # a flag wins over --config
    if online or online_table is not None:
        if data is not None:
            _fail("give exactly one source of training data: --data DATASET or --online (an [online] table)")
        from tt.dit.online import OnlineConfig

        online_config = OnlineConfig(**{"seed": settings.get("seed", 0), **(online_table or {})})
    else:
        if data is None:
            _fail("give exactly one source of training data: --data DATASET or --online")
        if not data.exists():
            _fail(f"--data {data} does not exist (a dataset folder from `tt generate`, or an episode token file)")
        online_config = None
    _output(out, "--out", folder=True)
    selector = None
    if selection is not None:
        from tt.dit.tasks import task_names
        from tt.selection import CheckpointSelector, SelectionConfig

        if not {"robot", "dynamics"} & set(task_names(settings.get("task", "robot"))):
            _fail("[selection] scores the model as a critic, which needs a task with robot or dynamics")
        selector = CheckpointSelector(out, SelectionConfig(**{"device": device, **selection}), fresh=not resume)
    episodes = None
    if online_config is not None:  # built here: the generator's sampler (proposals) lives above dit
        from tt.dit.train import DataParallel
        from tt.guidance.proposer import online_source

        episodes = online_source(online_config, device, progress=DataParallel.reports())
    result = train_cmd(
        data,
        out=out,
        episodes=episodes,
        device=device,
        resume=resume,
        init=init,
        online=online_config,
        on_checkpoint=selector,
        on_start_over=selector.start_over if selector is not None else None,
        **settings,
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
            f"best checkpoint on {selector.config.designs} held-out designs: step {b.step}, within-motion r "
            f"{b.within_r:.3f}, pooled r {b.pooled_r:.3f}: {selector.best_path}"
        )


def train_settings(config: list[str] | None, init: Path | None = None, **flags) -> dict:
    """The settings `tt train` gives `TrainConfig` (plus its ``online`` and ``selection``
    tables): the --init checkpoint's network and layout (`tt.dit.train.init_settings`), then
    the --config items in order, then the flags given (None: not given)."""
    from tt.dit.train import init_settings

    settings = _config(config, _train_keys(), "--config")
    if init is not None:
        task = flags.get("task") or settings.get("task", "robot")
        settings = {**init_settings(init, task), **settings}
    settings.update({k: v for k, v in flags.items() if v is not None})
    return settings


def _train_keys() -> dict:
    """`tt train --config`'s keys: `TrainConfig`'s fields but those its flags set, and the
    tables [online] (`OnlineConfig`) and [selection] (`SelectionConfig`)."""
    from tt.dit.online import OnlineConfig
    from tt.dit.train import TrainConfig
    from tt.selection import SelectionConfig

    keys = _fields(TrainConfig, exclude=("data", "out", "device", "resume", "init", "online"))
    keys["online"] = _fields(OnlineConfig)
    keys["selection"] = _fields(SelectionConfig, exclude=("device",))
    return keys


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
    workers: int = typer.Option(1, help="Shards generated at once: worker processes, or the CPUs of ray=local."),
    seed: int = typer.Option(0, help="Random seed; every shard derives its draws from (seed, shard index)."),
    config: Optional[List[str]] = typer.Option(
        None,
        "--config",
        help="More settings: KEY=VALUE or a TOML / JSON file (repeatable), e.g. select=32, bias=cmaes.",
    ),
) -> None:
    """Generate a RoboToken dataset: sample designs, roll out, filter, tokenize, write shards.

    \f
    `--config` takes the keyword arguments of `tt.generate.generate_cmd` that have no flag
    (each checked by `tt.tokens.draws.GenerateConfig`, an unknown key refused naming the valid
    ones):

    - `select=K`: designs screened per kept episode: each motion of a rollout group keeps the
      best 1/K of the group's designs on it (`--designs` counts the screen), so the data pairs
      motions with designs chosen for them; 1 (default): every episode. `uniform_share=F`:
      the share of each motion's kept episodes drawn uniformly from the screen instead of the
      best (a critic still sees failures).
    - `bias="cmaes"`: the paper's data biasing (CMA-ES, population 5, 3 generations per
      training motion).
    - `action_noise=SIGMA`: the control perturbation, the standard deviation [rad or m] of
      Gaussian noise on the executed commands, clean ones logged (default:
      tt.tokens.draws.DEFAULT_ACTION_NOISE = 0.01 on warp spaces; 0: none).
    - `ray="local"` or a cluster address: distribute shards as Ray tasks (pip install 'tt[ray]').
    - `designs_per_shard` (1024): the unit of resume and of distribution; `min_steps` (100 =
      2 s): shorter episodes are dropped; `max_motion_steps`: cut training motions; `threads`:
      CPU threads of each worker's warp rollouts (default: the cores shared out over
      `--workers`; the dataset is the same for any count).
    """
    from tt.generate import generate_cmd

    keys = _signature_keys(
        generate_cmd,
        exclude=("space", "designs", "out", "episodes_per_design", "device", "workers", "seed", "progress"),
    )
    settings = _config(config, keys, "--config")
    _at_least("--designs", designs, 1)
    _at_least("--episodes-per-design", episodes_per_design, 1)
    _at_least("--workers", workers, 1)
    _output(out, "--out", folder=True)
    typer.echo(
        generate_cmd(
            space,
            designs,
            out,
            episodes_per_design=episodes_per_design,
            device=device,
            workers=workers,
            seed=seed,
            **settings,
        )
    )


def _signature_keys(fn, exclude: tuple[str, ...] = ()) -> dict[str, str]:
    """A function's keyword parameters (name -> annotation text), those in `exclude` left out:
    the keys `_config` accepts for it."""
    import inspect

    return {
        n: p.annotation.__name__ if isinstance(p.annotation, type) else str(p.annotation)
        for n, p in inspect.signature(fn).parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY and n not in exclude
    }


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
        None, help="Target motion (library name or file; default: the space's, toss or bi_fling; aloha: bi_fling:100)."
    ),
    reward: Optional[str] = typer.Option(
        None, help=_REWARD_HELP + " Default: the space's, tracking; aloha: tracking_velocity.", callback=_reward
    ),
    budget: int = typer.Option(64, help="Candidate designs for Random and CMA-ES."),
    out: Path = typer.Option(Path("tt_demo"), help="Folder for demo.json and demo.html."),
    config: Optional[List[str]] = typer.Option(
        None,
        "--config",
        help="More settings (`tt.demo.DemoConfig`): KEY=VALUE or a TOML / JSON file (repeatable), e.g. "
        '\'methods=["random", "zeroth"]\', samples=8, num_steps=10, checkpoint=PATH, seed=1, device=cuda.',
    ),
) -> None:
    """The main job: co-design a robot for a motion with every method; validate; show the winners.

    Random and batched CMA-ES run; Zeroth-Order, Dynamics Self-Guidance and Zeroth + sim
    run when the space has a shipped DiT checkpoint (or --config checkpoint=PATH is given),
    with `samples` candidates of `num_steps` DDIM steps (`methods` picks which run). --space
    aloha: the paper's ALOHA experiment on a fling, the original ALOHA validated beside the
    optimized designs (its Self-Guidance follows the critic through every candidate's decoded
    design at every step: about 2 minutes on a 2-core CPU)."""
    from tt.demo import DemoConfig, run_demo
    from tt.report import columns_for, rich_table

    _at_least("--budget", budget, 1)
    settings = _config(config, _fields(DemoConfig, exclude=("space", "motion", "reward", "budget", "out")), "--config")
    demo_config = DemoConfig(space=space, motion=motion, reward=reward, budget=budget, out=out, **settings)
    _output(out, "--out", folder=True)
    rows = run_demo(demo_config, echo=typer.echo)
    space, motion, reward = demo_config.space, demo_config.motion, demo_config.reward
    extra = [("seconds", "optimize (s)"), ("rollouts", "rollouts")] + (
        [("note", "note")] if any("note" in r for r in rows) else []
    )
    _console().print(
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
    path: str = typer.Argument(..., help="Tokens .npz (from `tt tokenize --out`), or tokens.npz#i for robot i."),
    out: Path = typer.Option(..., help="Write the robot's MJCF here (-: stdout)."),
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
    file, hash_, tail = path.rpartition("#") if "#" in path else (path, "", "0")
    try:
        index = int(tail)
    except ValueError:
        _fail(f"{path}: the robot after '#' must be an integer index (tokens.npz#i), got {tail!r}")
    typer.echo(detokenize_cmd(file, str(out), index=index, space=space, project=project), err=quiet)


def _space_ok(space: str) -> bool:
    from tt.sim.designs import SPACE_NAMES

    return space in SPACE_NAMES


def main() -> None:
    app()


if __name__ == "__main__":
    main()
