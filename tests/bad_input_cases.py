"""Bad inputs for every ``tt`` command, shared by ``tests/test_bad_inputs.py`` and the sweep
``benchmarks/bad_inputs.py``.

`make_files` writes good files and damaged, truncated, foreign or odd ones into a folder;
`CASES` is the table: each case is a command line over those files, the class of failure
of issue 22 it belongs to, what the one-line error must name (or, for inputs that are odd
but valid, that the command succeeds), and an optional check of what is on disk after it.
`outcome` runs one case through the real CLI and says how it went.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np

#: Classes of failure of issue 22.
CLASSES = {
    1: "corrupt or foreign file",
    2: "resume from a damaged latest file",
    3: "output path created late",
    4: "garbage reported as success",
    5: "data loss and leaks",
    6: "misleading message",
    7: "detokenizer names",
}

#: Words of torch's and numpy's advice about loading pickles; no message may carry them.
PICKLE_ADVICE = ("allow_pickle", "weights_only", "untrusted")


@dataclass
class Case:
    """One bad input. args(files) -> command line; expect: substrings the error names (each
    formatted with the files' attributes, e.g. "{root}"); ok: the command must succeed
    (odd but valid input); check(files, output) -> None or what went wrong on disk."""

    name: str
    cls: int
    args: Callable[[SimpleNamespace], list[str]]
    expect: tuple[str, ...] = ()
    ok: bool = False
    check: Callable[[SimpleNamespace, str], str | None] | None = None
    slow: bool = False
    setup: Callable[[SimpleNamespace], None] | None = field(default=None, repr=False)


def _truncate(src: Path, dst: Path, keep: float = 0.5) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * keep)])
    return dst


def _savez(path: Path, **arrays) -> Path:
    with open(path, "wb") as f:  # np.savez appends .npz to names without it
        np.savez(f, **arrays)
    return path


def make_files(root: Path, dataset: Path | None = None) -> SimpleNamespace:
    """Good and bad input files under `root`; `dataset`: a small finished `tt generate`
    dataset (copied, then damaged), or None to leave the dataset cases out."""
    import torch

    from tt.dit.checkpoint import CHECKPOINT_FORMAT
    from tt.dit.toy import toy_episodes
    from tt.sim.designs import get_space, save_designs
    from tt.sim.motions import get_motion, save_npz
    from tt.sim.motions.base import Motion
    from tt.tokens.tokenize import tokenize_models

    root.mkdir(parents=True, exist_ok=True)
    f = SimpleNamespace(root=str(root))

    def put(name: str, path: Path) -> None:
        setattr(f, name, str(path))

    sp = get_space("viperx")
    save_designs(sp.sample(2, 0), root / "designs.json")
    put("designs", root / "designs.json")
    data = json.loads((root / "designs.json").read_text())
    key = next(iter(data["designs"][1]["continuous"]))
    data["designs"][1]["continuous"][key] = 99.0
    (root / "designs_bad1.json").write_text(json.dumps(data))
    put("designs_bad1", root / "designs_bad1.json")
    (root / "designs_garbage.json").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe")
    put("designs_garbage", root / "designs_garbage.json")
    put("designs_truncated", _truncate(root / "designs.json", root / "designs_truncated.json"))
    (root / "designs_space.json").write_text(json.dumps({"designs": [{"space": "cheetah", "discrete": {}, "continuous": {}}]}))
    put("designs_space", root / "designs_space.json")
    (root / "designs_empty.json").write_text('{"designs": []}')
    put("designs_empty", root / "designs_empty.json")

    toss = get_motion("toss")
    short = Motion("toss_short", toss.pos[:20], toss.quat[:20], toss.dt)
    save_npz(short, root / "motion.npz")
    put("motion", root / "motion.npz")
    put("motion_truncated", _truncate(root / "motion.npz", root / "motion_truncated.npz"))
    put("motion_pickle", _savez(root / "motion_pickle.npz", pos=np.array([{"a": 1}], dtype=object)))
    nan = short.pos[:, 0].copy()
    nan[5, 2] = np.nan
    put("motion_nan", _savez(root / "motion_nan.npz", pos=nan, quat=short.quat[:, 0], dt=np.float64(short.dt)))
    np.save(root / "motion_npy.npy", short.pos[:, 0])
    shutil.move(root / "motion_npy.npy", root / "motion_npy.npz")
    put("motion_npy", root / "motion_npy.npz")
    put("motion_dt", _savez(root / "motion_dt.npz", pos=short.pos[:, 0], quat=short.quat[:, 0], dt=np.array([0.02, 0.02])))
    # 5 m up: motion files are placed over the base on load, and placing keeps heights.
    far = Motion("far", short.pos + np.array([0.0, 0.0, 5.0]), short.quat, short.dt)
    save_npz(far, root / "motion_far.npz")
    put("motion_far", root / "motion_far.npz")

    tokens = tokenize_models([sp.model(sp.nominal())]).tokens
    tokens.save(root / "tokens.npz")
    put("tokens", root / "tokens.npz")
    arrays = dict(np.load(root / "tokens.npz"))
    bad = dict(arrays)
    bad["link/values"] = bad["link/values"].copy()
    bad["link/values"][0, 1, 0] = np.nan
    put("tokens_nan", _savez(root / "tokens_nan.npz", **bad))
    put("tokens_nokey", _savez(root / "tokens_nokey.npz", **{k: v for k, v in arrays.items() if k != "link/mask"}))
    put("tokens_v1", _savez(root / "tokens_v1.npz", **dict(arrays, schema_version=np.array("v1"))))
    put("tokens_truncated", _truncate(root / "tokens.npz", root / "tokens_truncated.npz"))

    toy_episodes(episodes=6, steps=12, seed=0).save(root / "episodes.npz")
    put("episodes", root / "episodes.npz")
    put("episodes_truncated", _truncate(root / "episodes.npz", root / "episodes_truncated.npz"))

    (root / "ckpt_empty.pt").write_bytes(b"")
    put("ckpt_empty", root / "ckpt_empty.pt")
    torch.save({"format": CHECKPOINT_FORMAT, "step": 3, "weights": torch.zeros(64)}, root / "ckpt_nokey.pt")
    put("ckpt_nokey", root / "ckpt_nokey.pt")
    put("ckpt_truncated", _truncate(root / "ckpt_nokey.pt", root / "ckpt_truncated.pt", 0.6))
    torch.save({"weights": torch.zeros(4)}, root / "ckpt_foreign.pt")
    put("ckpt_foreign", root / "ckpt_foreign.pt")
    torch.save({"format": CHECKPOINT_FORMAT, "schema_version": "v1"}, root / "ckpt_v1.pt")
    put("ckpt_v1", root / "ckpt_v1.pt")
    (root / "ckpt_pickle.pt").write_bytes(b"\x80\x04\x95" + b"\x00" * 40)
    put("ckpt_pickle", root / "ckpt_pickle.pt")

    (root / "robots_dir").mkdir(exist_ok=True)
    put("robots_dir", root / "robots_dir")
    (root / "empty.xml").write_bytes(b"")
    put("empty_xml", root / "empty.xml")
    (root / "garbage.xml").write_bytes(b"\x00\xff\xfe<mujoco")
    put("garbage_xml", root / "garbage.xml")
    (root / "episode_garbage.npz").write_bytes(b"PK\x03\x04garbage")
    put("episode_garbage", root / "episode_garbage.npz")
    (root / "afile").write_text("a file where a folder should be")
    put("afile", root / "afile")
    (root / "foreign").mkdir(exist_ok=True)
    (root / "foreign" / "notes.txt").write_text("someone's notes")
    put("foreign", root / "foreign")
    put("missing", root / "missing" / "deeper")

    if dataset is not None:
        flipped = root / "ds_flipped"
        shutil.copytree(dataset, flipped)
        chunk = flipped / "shards" / "s000001" / "episode" / "reward" / "c" / "0"
        raw = bytearray(chunk.read_bytes())
        raw[8] ^= 0xFF  # inside the blosc header: the chunk no longer decodes
        chunk.write_bytes(bytes(raw))
        put("dataset", dataset)
        put("ds_flipped", flipped)
    return f


def _stale_designs_removed(f: SimpleNamespace, out: str) -> str | None:
    folder = Path(f.root) / "designs_out"
    stale = folder / "viperx_0003.xml"
    if stale.exists():
        return "a design file of the earlier run is left beside the new designs.json"
    if not (folder / "mine.txt").exists():
        return "a file tt did not write was removed"
    return None


def _earlier_designs(f: SimpleNamespace) -> None:
    from typer.testing import CliRunner

    from tt.cli import app

    folder = Path(f.root) / "designs_out"
    CliRunner().invoke(app, ["designs", "--n", "4", "--out", str(folder)])
    (folder / "mine.txt").write_text("kept")


V = ["validate", "--design"]
CASES: list[Case] = [
    # -- 1: corrupt or foreign files, every reader
    Case("validate: designs.json of binary garbage", 1, lambda f: [*V, f.designs_garbage, "--motion", "toss"], ("designs_garbage.json", "not text")),
    Case("validate: truncated designs.json", 1, lambda f: [*V, f.designs_truncated, "--motion", "toss"], ("designs_truncated.json", "not valid JSON")),
    Case("validate: unknown space in designs.json", 1, lambda f: [*V, f.designs_space, "--motion", "toss"], ("designs_space.json", "cheetah")),
    Case("validate: designs.json with no designs", 1, lambda f: [*V, f.designs_empty, "--motion", "toss"], ("designs_empty.json", "no designs")),
    Case("validate: truncated motion file", 1, lambda f: [*V, f.designs, "--motion-file", f.motion_truncated], ("motion_truncated.npz", "truncated")),
    Case("validate: motion file holding pickled objects", 1, lambda f: [*V, f.designs, "--motion-file", f.motion_pickle], ("motion_pickle.npz", "Python objects")),
    Case("validate: motion file that is one .npy array", 1, lambda f: [*V, f.designs, "--motion-file", f.motion_npy], ("motion_npy.npz", ".npy")),
    Case("validate: motion file with two dt values", 1, lambda f: [*V, f.designs, "--motion-file", f.motion_dt], ("motion_dt.npz", "'dt'")),
    Case("validate: motion file with NaN", 1, lambda f: [*V, f.designs, "--motion-file", f.motion_nan], ("motion_nan.npz", "NaN")),
    Case("validate: motion file that does not exist", 1, lambda f: [*V, f.designs, "--motion-file", f.root + "/nope.npz"], ("nope.npz", "no such file")),
    Case("validate: truncated checkpoint for --controller model", 1,
         lambda f: [*V, f.designs, "--motion-file", f.motion, "--controller", "model", "--checkpoint", f.ckpt_truncated, "--device", "cpu"],
         ("ckpt_truncated.pt", "truncated")),
    Case("rollout: truncated designs.json", 1, lambda f: ["rollout", "--design", f.designs_truncated], ("designs_truncated.json",)),
    Case("rollout: motion file of garbage", 1, lambda f: ["rollout", "--n", "1", "--motion-file", f.garbage_xml], ("garbage.xml", "unknown motion file type")),
    Case("optimize: pickled motion file", 1, lambda f: ["optimize", "--motion-file", f.motion_pickle], ("motion_pickle.npz",)),
    Case("optimize: empty checkpoint for zeroth", 1, lambda f: ["optimize", "--method", "zeroth", "--motion", "toss", "--checkpoint", f.ckpt_empty, "--device", "cpu"],
         ("ckpt_empty.pt", "empty")),
    Case("view: episode file of garbage", 1, lambda f: ["view", f.episode_garbage, "--html", f.root + "/v.html"], ("episode_garbage.npz",)),
    Case("view: truncated designs.json", 1, lambda f: ["view", f.designs_truncated, "--html", f.root + "/v.html"], ("designs_truncated.json",)),
    Case("view: pickled motion file as --motion", 1, lambda f: ["view", f.designs, "--motion", f.motion_pickle, "--html", f.root + "/v.html"], ("motion_pickle.npz",)),
    Case("tokenize: empty MJCF file", 1, lambda f: ["tokenize", f.empty_xml], ("empty.xml", "empty")),
    Case("tokenize: MJCF of binary garbage", 1, lambda f: ["tokenize", f.garbage_xml], ("garbage.xml", "MuJoCo cannot load")),
    Case("tokenize: designs.json of garbage", 1, lambda f: ["tokenize", f.designs_garbage], ("designs_garbage.json",)),
    Case("detokenize: truncated token file", 1, lambda f: ["detokenize", f.tokens_truncated, "--out", f.root + "/r.xml"], ("tokens_truncated.npz", "truncated")),
    Case("detokenize: token file lacking a key", 1, lambda f: ["detokenize", f.tokens_nokey, "--out", f.root + "/r.xml"], ("tokens_nokey.npz", "link/mask")),
    Case("detokenize: a motion file as token file", 1, lambda f: ["detokenize", f.motion, "--out", f.root + "/r.xml"], ("motion.npz", "not a RoboToken file")),
    Case("train: truncated episode token file", 1, lambda f: ["train", "--data", f.episodes_truncated, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_t"],
         ("episodes_truncated.npz", "truncated")),
    Case("train: a motion file as --data", 1, lambda f: ["train", "--data", f.motion, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_m"], ("motion.npz", "header")),
    Case("train: truncated checkpoint as --init", 1, lambda f: ["train", "--data", f.episodes, "--init", f.ckpt_truncated, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_i"],
         ("ckpt_truncated.pt", "truncated")),
    Case("train: checkpoint lacking keys as --init", 1, lambda f: ["train", "--data", f.episodes, "--init", f.ckpt_nokey, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_k"],
         ("ckpt_nokey.pt", "'model'")),
    Case("train: foreign torch file as --init", 1, lambda f: ["train", "--data", f.episodes, "--init", f.ckpt_foreign, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_f"],
         ("ckpt_foreign.pt", "not a tt DiT checkpoint")),
    Case("train: pickle bytes as --init", 1, lambda f: ["train", "--data", f.episodes, "--init", f.ckpt_pickle, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_p"],
         ("ckpt_pickle.pt",)),
    Case("dataset info: a chunk with a flipped byte", 1, lambda f: ["dataset", "info", f.ds_flipped], ("s000001", "episode/reward", "tt dataset verify")),
    Case("dataset verify: a chunk with a flipped byte", 1, lambda f: ["dataset", "verify", f.ds_flipped], ("s000001", "CRC-32")),
    Case("dataset info: a folder that is no dataset", 1, lambda f: ["dataset", "info", f.foreign], ("foreign", "not a tt dataset")),
    Case("generate: --out over a folder of other files", 1, lambda f: ["generate", "--designs", "1", "--out", f.foreign], ("foreign", "not a tt dataset")),
    # -- 3: outputs created before the work, or refused up front
    Case("motions --out into missing folders", 3, lambda f: ["motions", "--name", "toss", "--out", f.missing + "/toss.npz"], ok=True,
         check=lambda f, out: None if Path(f.missing, "toss.npz").exists() else "toss.npz not written"),
    Case("tokenize --out into missing folders", 3, lambda f: ["tokenize", f.designs, "--out", f.missing + "/t.npz"], ok=True,
         check=lambda f, out: None if Path(f.missing, "t.npz").exists() else "t.npz not written"),
    Case("validate --json onto an existing folder", 3, lambda f: [*V, f.designs, "--motion", "toss", "--json", f.robots_dir], ("--json", "robots_dir", "is a folder")),
    Case("predict: truncated checkpoint", 1, lambda f: ["predict", "--design", f.designs + "#0", "--motion", "toss", "--checkpoint", f.ckpt_truncated, "--device", "cpu"],
         ("ckpt_truncated.pt",)),
    Case("predict: garbage designs.json", 1, lambda f: ["predict", "--design", f.designs_garbage, "--motion", "toss"], ("designs_garbage.json",)),
    Case("predict --json under a file", 3, lambda f: ["predict", "--design", f.designs + "#0", "--motion", "toss", "--json", f.afile + "/x.json"],
         ("--json", "afile")),
    Case("predict --samples 0 names the flag", 6, lambda f: ["predict", "--design", f.designs + "#0", "--motion", "toss", "--samples", "0"],
         ("--samples",)),
    Case("optimize --json under a file", 3, lambda f: ["optimize", "--motion", "toss", "--json", f.afile + "/x.json"], ("--json", "afile")),
    Case("rollout --out onto a file", 3, lambda f: ["rollout", "--n", "1", "--out", f.afile], ("--out", "afile", "is a file")),
    Case("designs --out under a file", 3, lambda f: ["designs", "--n", "1", "--out", f.afile + "/d"], ("--out", "afile")),
    Case("dataset info --plot under a file", 3, lambda f: ["dataset", "info", f.foreign, "--plot", f.afile + "/p.png"], ("--plot", "afile")),
    Case("view --html under a file", 3, lambda f: ["view", f.designs, "--html", f.afile + "/v.html"], ("--html", "afile")),
    Case("demo --out onto a file", 3, lambda f: ["demo", "--out", f.afile], ("--out", "afile", "is a file")),
    Case("train --out onto a file", 3, lambda f: ["train", "--data", f.episodes, "--size", "tiny", "--steps", "1", "--out", f.afile], ("--out", "afile")),
    Case("generate --out onto a file", 3, lambda f: ["generate", "--designs", "1", "--out", f.afile], ("--out", "afile")),
    Case("detokenize --out onto a folder", 3, lambda f: ["detokenize", f.tokens, "--out", f.robots_dir], ("--out", "robots_dir", "is a folder")),
    Case("validate --json into missing folders", 3, lambda f: [*V, f.designs + "#0", "--motion-file", f.motion, "--json", f.missing + "/v.json"], ok=True,
         check=lambda f, out: _strict_json(Path(f.missing, "v.json"))),
    # -- 4: garbage reported as success
    Case("detokenize: NaN inside a real token", 4, lambda f: ["detokenize", f.tokens_nan, "--out", f.root + "/r.xml"], ("tokens_nan.npz", "NaN", "'link'")),
    Case("optimize: no candidate survives a step", 4, lambda f: ["optimize", "--method", "random", "--budget", "3", "--motion-file", f.motion_far],
         ("no candidate", "survived")),
    Case("train: a dataset chunk failing its checksum", 4, lambda f: ["train", "--data", f.ds_flipped, "--size", "tiny", "--steps", "1", "--batch-size", "2",
                                                                      "--out", f.root + "/run_ds"], ok=True,
         check=lambda f, out: None if "damaged shard s000001" in out else "no warning about the damaged shard"),
    # -- 5: data loss and leaks
    Case("designs --out over an earlier run's folder", 5, lambda f: ["designs", "--n", "2", "--out", f.root + "/designs_out"], ok=True,
         check=_stale_designs_removed, setup=_earlier_designs),
    # -- 6: misleading messages
    Case("validate: an error in design #1 of 2", 6, lambda f: [*V, f.designs_bad1, "--motion", "toss"], ("design #1 of 2", "99.0")),
    Case("validate: design index out of range", 6, lambda f: [*V, f.designs + "#5", "--motion", "toss"], ("index 5", "holds 2")),
    Case("optimize --budget 0 names the flag", 6, lambda f: ["optimize", "--motion", "toss", "--budget", "0"], ("--budget",)),
    Case("optimize --popsize 1 names the flag", 6, lambda f: ["optimize", "--motion", "toss", "--popsize", "1"], ("--popsize",)),
    Case("optimize --method nope lists the methods", 6, lambda f: ["optimize", "--motion", "toss", "--method", "nope"], ("random", "cmaes", "zeroth", "dgs")),
    Case("optimize --samples 0 names the flag", 6, lambda f: ["optimize", "--motion", "toss", "--method", "zeroth", "--samples", "0"], ("--samples",)),
    Case("optimize --guide-by nope lists the sources", 6, lambda f: ["optimize", "--motion", "toss", "--method", "dgs", "--guide-by", "nope"], ("--guide-by", "model", "critic")),
    Case("optimize --guide-by critic for cmaes names the flag", 6, lambda f: ["optimize", "--motion", "toss", "--guide-by", "critic"], ("--guide-by", "dgs")),
    Case("optimize --critic-at nope lists the places", 6, lambda f: ["optimize", "--motion", "toss", "--method", "dgs", "--guide-by", "critic", "--critic-at", "nope"], ("--critic-at", "tokens", "design", "project")),
    Case("optimize --critic-at project without --scale", 6, lambda f: ["optimize", "--motion", "toss", "--method", "dgs", "--guide-by", "critic", "--critic-at", "project"], ("--critic-at project", "--scale")),
    Case("optimize --refine below 0 names the flag", 6, lambda f: ["optimize", "--motion", "toss", "--method", "zeroth", "--refine", "-1"], ("--refine", ">= 0")),
    Case("optimize --refine for cmaes names the methods", 6, lambda f: ["optimize", "--motion", "toss", "--refine", "3"], ("--refine", "zeroth or dgs", "cmaes")),
    Case("optimize --refine with the joint critic", 6, lambda f: ["optimize", "--motion", "toss", "--method", "zeroth", "--critic", "joint", "--refine", "3"], ("--refine", "dynamics critic", "--critic joint")),
    Case("optimize --critic-at design without --guide-by critic", 6, lambda f: ["optimize", "--motion", "toss", "--method", "dgs", "--critic-at", "design"], ("--critic-at", "--guide-by critic")),
    Case("rollout --n 0 names the flag", 6, lambda f: ["rollout", "--n", "0"], ("--n",)),
    Case("designs --n 0 names the flag", 6, lambda f: ["designs", "--n", "0", "--out", f.root + "/d0"], ("--n",)),
    Case("generate --designs 0 names the flag", 6, lambda f: ["generate", "--designs", "0", "--out", f.root + "/g0"], ("--designs",)),
    Case("generate --workers 0 names the flag", 6, lambda f: ["generate", "--designs", "1", "--workers", "0", "--out", f.root + "/g0"], ("--workers",)),
    Case("train --steps 0 names the flag", 6, lambda f: ["train", "--data", f.episodes, "--steps", "0", "--out", f.root + "/r0"], ("--steps",)),
    Case("train --batch-size 0 names the flag", 6, lambda f: ["train", "--data", f.episodes, "--batch-size", "0", "--out", f.root + "/r0"], ("--batch-size",)),
    Case("train --lr -1 names the flag", 6, lambda f: ["train", "--data", f.episodes, "--lr", "-1", "--out", f.root + "/r0"], ("--lr",)),
    Case("train --data that does not exist", 6, lambda f: ["train", "--data", f.root + "/nothing", "--out", f.root + "/r0"], ("--data", "nothing")),
    Case("demo --budget 0 names the flag", 6, lambda f: ["demo", "--budget", "0", "--out", f.root + "/demo"], ("--budget",)),
    Case("tokenize: a folder as MJCF path", 6, lambda f: ["tokenize", f.robots_dir], ("robots_dir", "is a folder")),
    Case("detokenize: an empty checkpoint-like file as tokens", 6, lambda f: ["detokenize", f.ckpt_empty, "--out", f.root + "/r.xml"], ("ckpt_empty.pt", "empty")),
    Case("train: empty checkpoint as --init", 6, lambda f: ["train", "--data", f.episodes, "--init", f.ckpt_empty, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_e"],
         ("ckpt_empty.pt", "empty")),
    Case("train: checkpoint with schema_version 'v1'", 6, lambda f: ["train", "--data", f.episodes, "--init", f.ckpt_v1, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_v"],
         ("ckpt_v1.pt", "'v1'", "not an integer")),
    Case("detokenize: token file with schema_version 'v1'", 6, lambda f: ["detokenize", f.tokens_v1, "--out", f.root + "/r.xml"], ("tokens_v1.npz", "'v1'", "not an integer")),
    Case("detokenize --index 3 of a one-robot file", 6, lambda f: ["detokenize", f.tokens, "--out", f.root + "/r.xml", "--index", "3"], ("index 3", "1 robot")),
    Case("view: design index out of range", 6, lambda f: ["view", f.designs + "#7", "--html", f.root + "/v.html"], ("index 7",)),
    Case("generate: unknown space", 6, lambda f: ["generate", "--space", "cheetah", "--designs", "1", "--out", f.root + "/g1"], ("cheetah", "viperx")),
    Case("rollout: unknown backend", 6, lambda f: ["rollout", "--n", "1", "--backend", "bullet"], ("bullet", "warp")),
    Case("validate: unknown reward", 6, lambda f: [*V, f.designs, "--motion", "toss", "--reward", "speed"], ("speed",)),
    Case("motions --name nope", 6, lambda f: ["motions", "--name", "nope", "--out", f.root + "/m.npz"], ("nope",)),
]


def _strict_json(path: Path) -> str | None:
    """None if `path` exists and parses as strict JSON (no bare NaN), else what is wrong."""
    if not path.exists():
        return f"{path} was not written"

    def reject(constant: str):
        raise ValueError(f"bare {constant}")

    try:
        json.loads(path.read_text(), parse_constant=reject)
    except ValueError as e:
        return f"{path} is not strict JSON ({e})"
    return None


@dataclass
class Outcome:
    """How one case went: kind is clear | ok | traceback | silent | misleading | loss."""

    case: Case
    kind: str
    code: int
    output: str
    why: str = ""


def outcome(case: Case, files: SimpleNamespace, invoke: Callable[[list[str]], tuple[int, str]]) -> Outcome:
    """Run `case` through `invoke` (the tt_cli fixture's signature) and classify the result."""
    if case.setup is not None:
        case.setup(files)
    code, out = invoke(case.args(files))
    errors = [line for line in out.splitlines() if line.startswith("error: ")]
    if "Traceback" in out or "internal error" in out:
        return Outcome(case, "traceback", code, out, "a traceback or an internal error")
    if any(w in out for w in PICKLE_ADVICE):
        return Outcome(case, "misleading", code, out, "advice about loading pickles")
    try:
        problem = case.check(files, out) if case.check is not None else None
    except Exception as e:  # a check that cannot even read what the command left
        problem = f"{type(e).__name__}: {e}"
    if case.ok:
        if code != 0:
            return Outcome(case, "misleading", code, out, f"exit {code} for a valid input")
        return Outcome(case, "loss" if problem else "ok", code, out, problem or "")
    if code == 0:
        return Outcome(case, "silent", code, out, "exit 0 for a bad input")
    if len(set(errors)) != 1:
        return Outcome(case, "misleading", code, out, f"{len(set(errors))} distinct error lines")
    missing = [e for e in case.expect if e.format(**vars(files)) not in errors[0]]
    if missing:
        return Outcome(case, "misleading", code, out, f"the error does not name {missing}")
    if problem:
        return Outcome(case, "loss", code, out, problem)
    return Outcome(case, "clear", code, out)


def noisy_detokenized(sigmas=(0.3, 1.0, 3.0)):
    """Detokenizer results of 12 quadruped robots' normalised tokens under Gaussian noise of
    each sigma (class 7: names must stay unique at any noise); yields `DetokenizeResult`s."""
    import warnings

    from tt.sim.designs import get_space
    from tt.tokens.batch import TokenBatch
    from tt.tokens.detokenize import detokenize
    from tt.tokens.normalize import Normalizer
    from tt.tokens.tokenize import tokenize_models

    sp = get_space("quadruped")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tokens = tokenize_models([sp.model(d) for d in sp.sample(12, seed=3)]).tokens
    norm = Normalizer.fit(tokens)
    clean = norm.normalize(tokens)
    rng = np.random.default_rng(0)
    for sigma in sigmas:
        noisy = TokenBatch({k: (v + rng.normal(0, sigma, v.shape)).astype(np.float32) for k, v in clean.values.items()},
                           clean.ids, clean.mask)
        yield from detokenize(norm.denormalize(noisy, detect_padding=True))
