"""Bad inputs for every ``tt`` command, shared by ``tests/test_bad_inputs.py`` and the sweep
``benchmarks/bad_inputs.py``.

`make_files` writes good files and damaged, truncated, foreign or odd ones into a folder;
`CASES` is the table: each case is a command line over those files, the class of failure
of issue 22 (1-7) or of issue 50's second round (8-15) it belongs to, what the one-line
error must name (or, for inputs that are odd but valid, that the command succeeds), and an
optional check of what is on disk after it. `outcome` runs one case through the real CLI
and says how it went; no error may name a Python class or field (`INTERNAL_NAMES`).
`SCENARIOS` are the cases a table row cannot hold (a full disk, stdout, a regenerated
dataset, ...): each runs itself and says how it went; `tests/test_bad_inputs.py` and the
sweep run them too.
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
    8: "output written unsafely (links, devices, a full disk)",
    9: "- as stdout",
    10: "tt designs removes files it did not write",
    11: "run folder reused (--no-resume, two writers, --init)",
    12: "resume on other data at the same path",
    13: "workers outliving a killed run",
    14: "flag that does not apply, ignored",
    15: "message naming internals",
    16: "a motion shorter than the model's window scored past its end",
    17: "a dataset whose root zarr.json is damaged, its shards intact",
}

#: Words of Python internals (config classes and fields) no error line may carry: a message
#: names the flag or file instead.
INTERNAL_NAMES = (
    "GenerateConfig",
    "TrainConfig",
    "OnlineConfig",
    "DiTConfig",
    "SelectionConfig",
    "SamplerConfig",
    "config.steps",
    "arms must be 1, 2 or None",
)

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
    (root / "designs_space.json").write_text(
        json.dumps({"designs": [{"space": "cheetah", "discrete": {}, "continuous": {}}]})
    )
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
    put(
        "motion_dt",
        _savez(root / "motion_dt.npz", pos=short.pos[:, 0], quat=short.quat[:, 0], dt=np.array([0.02, 0.02])),
    )
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
    from tt.dit.train import TrainConfig, train

    with torch.random.fork_rng(devices=[]):  # a real (tiny, one-step) checkpoint of the toy episodes
        trained = train(
            TrainConfig(
                data=str(root / "episodes.npz"),
                out=str(root / "trained"),
                size="tiny",
                steps=1,
                batch_size=4,
                device="cpu",
            )
        ).checkpoint
    put("trained", trained)
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
    (root / "ckpt_random.pt").write_bytes(np.random.default_rng(50).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    put("ckpt_random", root / "ckpt_random.pt")

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

    # Output targets: a link to an existing file, a dangling link, a socket, a folder with a space.
    (root / "link_target.json").write_text("old content")
    (root / "link.json").symlink_to("link_target.json")
    put("link", root / "link.json")
    put("link_target", root / "link_target.json")
    (root / "dangling.npz").symlink_to("made_by_link.npz")
    put("dangling", root / "dangling.npz")
    put("dangling_target", root / "made_by_link.npz")
    import socket

    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(root / "sock"))
    sock.close()  # the socket file stays
    put("socket", root / "sock")
    (root / "with space").mkdir(exist_ok=True)
    put("spaced", root / "with space")
    # A folder no `tt designs` ran in, holding a user's files named as tt names MJCF files.
    (root / "user_designs").mkdir(exist_ok=True)
    (root / "user_designs" / "viperx_0001.xml").write_text("<mujoco model='mine'/>")
    (root / "user_designs" / "aloha_0007.xml").write_text("<mujoco model='also mine'/>")
    put("user_designs", root / "user_designs")
    # Run folders whose selection record is damaged.
    for name, content in (("run_sel_json", b'{"designs": 16, "motions":'), ("run_sel_csv", b"\xff\xfe\x00garbage")):
        (root / name).mkdir(exist_ok=True)
        (root / name / ("selection.json" if name.endswith("json") else "selection.csv")).write_bytes(content)
        put(name, root / name)

    if dataset is not None:
        flipped = root / "ds_flipped"
        shutil.copytree(dataset, flipped)
        chunk = flipped / "shards" / "s000001" / "episode" / "reward" / "c" / "0"
        raw = bytearray(chunk.read_bytes())
        raw[8] ^= 0xFF  # inside the blosc header: the chunk no longer decodes
        chunk.write_bytes(bytes(raw))
        put("dataset", dataset)
        put("ds_flipped", flipped)
        root_damaged = root / "ds_root"
        shutil.copytree(dataset, root_damaged)
        (root_damaged / "zarr.json").write_bytes((dataset / "zarr.json").read_bytes()[:50])  # a write cut short
        put("ds_root", root_damaged)
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


def _shipped_critic() -> Path:
    """A checkpoint of the viperx space trained on the dynamics task (a shipped one)."""
    from tt.dit.checkpoint import default_checkpoint

    return default_checkpoint("viperx", task="dynamics")


def _written_through(link: str, target: str):
    """A check: the link at files.<link> is still a link, and files.<target> holds what was written."""

    def check(f: SimpleNamespace, out: str) -> str | None:
        if not Path(getattr(f, link)).is_symlink():
            return f"{getattr(f, link)} was replaced by a regular file"
        data = Path(getattr(f, target)).read_bytes() if Path(getattr(f, target)).exists() else b""
        return None if data.startswith(b"PK") else f"{getattr(f, target)} does not hold the output"

    return check


def _user_designs_kept(f: SimpleNamespace, out: str) -> str | None:
    folder = Path(f.user_designs)
    for name, model in (("viperx_0001.xml", "mine"), ("aloha_0007.xml", "also mine")):
        if not (folder / name).exists() or model not in (folder / name).read_text():
            return f"the user's {name} was removed or overwritten"
    return None


V = ["validate", "--design"]
CASES: list[Case] = [
    # -- 1: corrupt or foreign files, every reader
    Case(
        "validate: designs.json of binary garbage",
        1,
        lambda f: [*V, f.designs_garbage, "--motion", "toss"],
        ("designs_garbage.json", "not text"),
    ),
    Case(
        "validate: truncated designs.json",
        1,
        lambda f: [*V, f.designs_truncated, "--motion", "toss"],
        ("designs_truncated.json", "not valid JSON"),
    ),
    Case(
        "validate: unknown space in designs.json",
        1,
        lambda f: [*V, f.designs_space, "--motion", "toss"],
        ("designs_space.json", "cheetah"),
    ),
    Case(
        "validate: designs.json with no designs",
        1,
        lambda f: [*V, f.designs_empty, "--motion", "toss"],
        ("designs_empty.json", "no designs"),
    ),
    Case(
        "validate: truncated motion file",
        1,
        lambda f: [*V, f.designs, "--motion", f.motion_truncated],
        ("motion_truncated.npz", "truncated"),
    ),
    Case(
        "validate: motion file holding pickled objects",
        1,
        lambda f: [*V, f.designs, "--motion", f.motion_pickle],
        ("motion_pickle.npz", "Python objects"),
    ),
    Case(
        "validate: motion file that is one .npy array",
        1,
        lambda f: [*V, f.designs, "--motion", f.motion_npy],
        ("motion_npy.npz", ".npy"),
    ),
    Case(
        "validate: motion file with two dt values",
        1,
        lambda f: [*V, f.designs, "--motion", f.motion_dt],
        ("motion_dt.npz", "'dt'"),
    ),
    Case(
        "validate: motion file with NaN",
        1,
        lambda f: [*V, f.designs, "--motion", f.motion_nan],
        ("motion_nan.npz", "NaN"),
    ),
    Case(
        "validate: motion file that does not exist",
        1,
        lambda f: [*V, f.designs, "--motion", f.root + "/nope.npz"],
        ("nope.npz", "no such file"),
    ),
    Case(
        "validate: a truncated checkpoint as --controller",
        1,
        lambda f: [
            *V,
            f.designs,
            "--motion",
            f.motion,
            "--controller",
            f.ckpt_truncated,
            "--device",
            "cpu",
        ],
        ("ckpt_truncated.pt", "truncated"),
    ),
    Case(
        "rollout: truncated designs.json",
        1,
        lambda f: ["rollout", "--design", f.designs_truncated],
        ("designs_truncated.json",),
    ),
    Case(
        "rollout: motion file of garbage",
        1,
        lambda f: ["rollout", "--n", "1", "--motion", f.garbage_xml],
        ("garbage.xml", "unknown motion file type"),
    ),
    Case(
        "optimize: pickled motion file",
        1,
        lambda f: ["optimize", "--motion", f.motion_pickle],
        ("motion_pickle.npz",),
    ),
    Case(
        "optimize: empty checkpoint for zeroth",
        1,
        lambda f: [
            "optimize",
            "--method",
            "zeroth",
            "--motion",
            "toss",
            "--checkpoint",
            f.ckpt_empty,
            "--device",
            "cpu",
        ],
        ("ckpt_empty.pt", "empty"),
    ),
    Case(
        "view: episode file of garbage",
        1,
        lambda f: ["view", f.episode_garbage, "--html", f.root + "/v.html"],
        ("episode_garbage.npz",),
    ),
    Case(
        "view: truncated designs.json",
        1,
        lambda f: ["view", f.designs_truncated, "--html", f.root + "/v.html"],
        ("designs_truncated.json",),
    ),
    Case(
        "view: pickled motion file as --motion",
        1,
        lambda f: ["view", f.designs, "--motion", f.motion_pickle, "--html", f.root + "/v.html"],
        ("motion_pickle.npz",),
    ),
    Case("tokenize: empty MJCF file", 1, lambda f: ["tokenize", f.empty_xml], ("empty.xml", "empty")),
    Case(
        "tokenize: MJCF of binary garbage",
        1,
        lambda f: ["tokenize", f.garbage_xml],
        ("garbage.xml", "MuJoCo cannot load"),
    ),
    Case("tokenize: designs.json of garbage", 1, lambda f: ["tokenize", f.designs_garbage], ("designs_garbage.json",)),
    Case(
        "detokenize: truncated token file",
        1,
        lambda f: ["detokenize", f.tokens_truncated, "--out", f.root + "/r.xml"],
        ("tokens_truncated.npz", "truncated"),
    ),
    Case(
        "detokenize: token file lacking a key",
        1,
        lambda f: ["detokenize", f.tokens_nokey, "--out", f.root + "/r.xml"],
        ("tokens_nokey.npz", "link/mask"),
    ),
    Case(
        "detokenize: a motion file as token file",
        1,
        lambda f: ["detokenize", f.motion, "--out", f.root + "/r.xml"],
        ("motion.npz", "not a RoboToken file"),
    ),
    Case(
        "train: truncated episode token file",
        1,
        lambda f: [
            "train",
            "--data",
            f.episodes_truncated,
            "--size",
            "tiny",
            "--steps",
            "1",
            "--out",
            f.root + "/run_t",
        ],
        ("episodes_truncated.npz", "truncated"),
    ),
    Case(
        "train: a motion file as --data",
        1,
        lambda f: ["train", "--data", f.motion, "--size", "tiny", "--steps", "1", "--out", f.root + "/run_m"],
        ("motion.npz", "header"),
    ),
    Case(
        "train: truncated checkpoint as --init",
        1,
        lambda f: [
            "train",
            "--data",
            f.episodes,
            "--init",
            f.ckpt_truncated,
            "--size",
            "tiny",
            "--steps",
            "1",
            "--out",
            f.root + "/run_i",
        ],
        ("ckpt_truncated.pt", "truncated"),
    ),
    Case(
        "train: checkpoint lacking keys as --init",
        1,
        lambda f: [
            "train",
            "--data",
            f.episodes,
            "--init",
            f.ckpt_nokey,
            "--size",
            "tiny",
            "--steps",
            "1",
            "--out",
            f.root + "/run_k",
        ],
        ("ckpt_nokey.pt", "'model'"),
    ),
    Case(
        "train: foreign torch file as --init",
        1,
        lambda f: [
            "train",
            "--data",
            f.episodes,
            "--init",
            f.ckpt_foreign,
            "--size",
            "tiny",
            "--steps",
            "1",
            "--out",
            f.root + "/run_f",
        ],
        ("ckpt_foreign.pt", "not a tt DiT checkpoint"),
    ),
    Case(
        "train: pickle bytes as --init",
        1,
        lambda f: [
            "train",
            "--data",
            f.episodes,
            "--init",
            f.ckpt_pickle,
            "--size",
            "tiny",
            "--steps",
            "1",
            "--out",
            f.root + "/run_p",
        ],
        ("ckpt_pickle.pt",),
    ),
    Case(
        "dataset info: a chunk with a flipped byte",
        1,
        lambda f: ["dataset", "info", f.ds_flipped],
        ("s000001", "episode/reward", "tt dataset verify"),
    ),
    Case(
        "dataset verify: a chunk with a flipped byte",
        1,
        lambda f: ["dataset", "verify", f.ds_flipped],
        ("s000001", "CRC-32"),
    ),
    Case(
        "dataset info: a folder that is no dataset",
        1,
        lambda f: ["dataset", "info", f.foreign],
        ("foreign", "not a tt dataset"),
    ),
    Case(
        "generate: --out over a folder of other files",
        1,
        lambda f: ["generate", "--designs", "1", "--out", f.foreign],
        ("foreign", "not a tt dataset"),
    ),
    Case(
        "dataset info: a dataset whose zarr.json is damaged",
        17,
        lambda f: ["dataset", "info", f.ds_root],
        ("{ds_root}/zarr.json", "damaged", "tt generate"),
    ),
    Case(
        "train on a dataset whose zarr.json is damaged",
        17,
        lambda f: ["train", "--data", f.ds_root, "--size", "tiny", "--steps", "1", "--out", f.root + "/run17"],
        ("{ds_root}/zarr.json", "damaged", "tt generate"),
    ),
    # -- 3: outputs created before the work, or refused up front
    Case(
        "motions --out into missing folders",
        3,
        lambda f: ["motions", "--name", "toss", "--out", f.missing + "/toss.npz"],
        ok=True,
        check=lambda f, out: None if Path(f.missing, "toss.npz").exists() else "toss.npz not written",
    ),
    Case(
        "tokenize --out into missing folders",
        3,
        lambda f: ["tokenize", f.designs, "--out", f.missing + "/t.npz"],
        ok=True,
        check=lambda f, out: None if Path(f.missing, "t.npz").exists() else "t.npz not written",
    ),
    Case(
        "validate --json onto an existing folder",
        3,
        lambda f: [*V, f.designs, "--motion", "toss", "--json", f.robots_dir],
        ("--json", "robots_dir", "is a folder"),
    ),
    Case(
        "predict: truncated checkpoint",
        1,
        lambda f: [
            "predict",
            "--design",
            f.designs + "#0",
            "--motion",
            "toss",
            "--checkpoint",
            f.ckpt_truncated,
            "--device",
            "cpu",
        ],
        ("ckpt_truncated.pt",),
    ),
    Case(
        "predict: garbage designs.json",
        1,
        lambda f: ["predict", "--design", f.designs_garbage, "--motion", "toss"],
        ("designs_garbage.json",),
    ),
    Case(
        "predict --json under a file",
        3,
        lambda f: ["predict", "--design", f.designs + "#0", "--motion", "toss", "--json", f.afile + "/x.json"],
        ("--json", "afile"),
    ),
    Case(
        "predict --samples 0 names the flag",
        6,
        lambda f: ["predict", "--design", f.designs + "#0", "--motion", "toss", "--samples", "0"],
        ("--samples",),
    ),
    Case(
        "optimize --json under a file",
        3,
        lambda f: ["optimize", "--motion", "toss", "--json", f.afile + "/x.json"],
        ("--json", "afile"),
    ),
    Case(
        "rollout --out onto a file",
        3,
        lambda f: ["rollout", "--n", "1", "--out", f.afile],
        ("--out", "afile", "is a file"),
    ),
    Case(
        "designs --out under a file", 3, lambda f: ["designs", "--n", "1", "--out", f.afile + "/d"], ("--out", "afile")
    ),
    Case(
        "dataset info --plot under a file",
        3,
        lambda f: ["dataset", "info", f.foreign, "--plot", f.afile + "/p.png"],
        ("--plot", "afile"),
    ),
    Case(
        "view --html under a file", 3, lambda f: ["view", f.designs, "--html", f.afile + "/v.html"], ("--html", "afile")
    ),
    Case("demo --out onto a file", 3, lambda f: ["demo", "--out", f.afile], ("--out", "afile", "is a file")),
    Case(
        "train --out onto a file",
        3,
        lambda f: ["train", "--data", f.episodes, "--size", "tiny", "--steps", "1", "--out", f.afile],
        ("--out", "afile"),
    ),
    Case(
        "generate --out onto a file", 3, lambda f: ["generate", "--designs", "1", "--out", f.afile], ("--out", "afile")
    ),
    Case(
        "detokenize --out onto a folder",
        3,
        lambda f: ["detokenize", f.tokens, "--out", f.robots_dir],
        ("--out", "robots_dir", "is a folder"),
    ),
    Case(
        "validate --json into missing folders",
        3,
        lambda f: [*V, f.designs + "#0", "--motion", f.motion, "--json", f.missing + "/v.json"],
        ok=True,
        check=lambda f, out: _strict_json(Path(f.missing, "v.json")),
    ),
    # -- 4: garbage reported as success
    Case(
        "detokenize: NaN inside a real token",
        4,
        lambda f: ["detokenize", f.tokens_nan, "--out", f.root + "/r.xml"],
        ("tokens_nan.npz", "NaN", "'link'"),
    ),
    Case(
        "optimize: no candidate survives a step",
        4,
        lambda f: ["optimize", "--method", "random", "--budget", "3", "--motion", f.motion_far],
        ("no candidate", "survived"),
    ),
    Case(
        "train: a dataset chunk failing its checksum",
        4,
        lambda f: [
            "train",
            "--data",
            f.ds_flipped,
            "--size",
            "tiny",
            "--steps",
            "1",
            "--batch-size",
            "2",
            "--out",
            f.root + "/run_ds",
        ],
        ok=True,
        check=lambda f, out: None if "damaged shard s000001" in out else "no warning about the damaged shard",
    ),
    # -- 5: data loss and leaks
    Case(
        "designs --out over an earlier run's folder",
        5,
        lambda f: ["designs", "--n", "2", "--out", f.root + "/designs_out"],
        ok=True,
        check=_stale_designs_removed,
        setup=_earlier_designs,
    ),
    # -- 6: misleading messages
    Case(
        "validate: an error in design #1 of 2",
        6,
        lambda f: [*V, f.designs_bad1, "--motion", "toss"],
        ("design #1 of 2", "99.0"),
    ),
    Case(
        "validate: design index out of range",
        6,
        lambda f: [*V, f.designs + "#5", "--motion", "toss"],
        ("index 5", "holds 2"),
    ),
    Case(
        "optimize --budget 0 names the flag",
        6,
        lambda f: ["optimize", "--motion", "toss", "--budget", "0"],
        ("--budget",),
    ),
    Case(
        "optimize --config popsize=1 names the key",
        6,
        lambda f: ["optimize", "--motion", "toss", "--config", "popsize=1"],
        ("popsize",),
    ),
    Case(
        "optimize --method nope lists the methods",
        6,
        lambda f: ["optimize", "--motion", "toss", "--method", "nope"],
        ("random", "cmaes", "zeroth", "dgs"),
    ),
    Case(
        "optimize --config samples=0 names the key",
        6,
        lambda f: ["optimize", "--motion", "toss", "--method", "zeroth", "--config", "samples=0"],
        ("samples",),
    ),
    Case(
        "optimize --config guide_by=nope lists the sources",
        6,
        lambda f: ["optimize", "--motion", "toss", "--method", "dgs", "--config", "guide_by=nope"],
        ("guide_by", "model", "critic"),
    ),
    Case(
        "optimize --config guide_by=critic for cmaes names the valid keys",
        6,
        lambda f: ["optimize", "--motion", "toss", "--config", "guide_by=critic"],
        ("guide_by", "popsize"),
    ),
    Case(
        "optimize --refine below 0 names the flag",
        6,
        lambda f: ["optimize", "--motion", "toss", "--method", "zeroth", "--refine", "-1"],
        ("--refine", ">= 0"),
    ),
    Case(
        "optimize --refine for cmaes names the methods",
        6,
        lambda f: ["optimize", "--motion", "toss", "--refine", "3"],
        ("--refine", "learned methods", "cmaes"),
    ),
    Case(
        "optimize --refine with the joint critic",
        6,
        lambda f: ["optimize", "--motion", "toss", "--method", "zeroth", "--config", "critic=joint", "--refine", "3"],
        ("refine", "dynamics critic", "critic = 'joint'"),
    ),
    Case("rollout --n 0 names the flag", 6, lambda f: ["rollout", "--n", "0"], ("--n",)),
    Case("designs --n 0 names the flag", 6, lambda f: ["designs", "--n", "0", "--out", f.root + "/d0"], ("--n",)),
    Case(
        "generate --designs 0 names the flag",
        6,
        lambda f: ["generate", "--designs", "0", "--out", f.root + "/g0"],
        ("--designs",),
    ),
    Case(
        "generate --workers 0 names the flag",
        6,
        lambda f: ["generate", "--designs", "1", "--workers", "0", "--out", f.root + "/g0"],
        ("--workers",),
    ),
    Case(
        "train --steps 0 names the flag",
        6,
        lambda f: ["train", "--data", f.episodes, "--steps", "0", "--out", f.root + "/r0"],
        ("--steps",),
    ),
    Case(
        "train --batch-size 0 names the flag",
        6,
        lambda f: ["train", "--data", f.episodes, "--batch-size", "0", "--out", f.root + "/r0"],
        ("--batch-size",),
    ),
    Case(
        "train --config lr=-1 names the key",
        6,
        lambda f: ["train", "--data", f.episodes, "--config", "lr=-1", "--out", f.root + "/r0"],
        ("lr",),
    ),
    Case(
        "train --data that does not exist",
        6,
        lambda f: ["train", "--data", f.root + "/nothing", "--out", f.root + "/r0"],
        ("--data", "nothing"),
    ),
    Case(
        "demo --budget 0 names the flag",
        6,
        lambda f: ["demo", "--budget", "0", "--out", f.root + "/demo"],
        ("--budget",),
    ),
    Case("tokenize: a folder as MJCF path", 6, lambda f: ["tokenize", f.robots_dir], ("robots_dir", "is a folder")),
    Case(
        "detokenize: an empty checkpoint-like file as tokens",
        6,
        lambda f: ["detokenize", f.ckpt_empty, "--out", f.root + "/r.xml"],
        ("ckpt_empty.pt", "empty"),
    ),
    Case(
        "train: empty checkpoint as --init",
        6,
        lambda f: [
            "train",
            "--data",
            f.episodes,
            "--init",
            f.ckpt_empty,
            "--size",
            "tiny",
            "--steps",
            "1",
            "--out",
            f.root + "/run_e",
        ],
        ("ckpt_empty.pt", "empty"),
    ),
    Case(
        "train: checkpoint with schema_version 'v1'",
        6,
        lambda f: [
            "train",
            "--data",
            f.episodes,
            "--init",
            f.ckpt_v1,
            "--size",
            "tiny",
            "--steps",
            "1",
            "--out",
            f.root + "/run_v",
        ],
        ("ckpt_v1.pt", "'v1'", "not an integer"),
    ),
    Case(
        "detokenize: token file with schema_version 'v1'",
        6,
        lambda f: ["detokenize", f.tokens_v1, "--out", f.root + "/r.xml"],
        ("tokens_v1.npz", "'v1'", "not an integer"),
    ),
    Case(
        "detokenize tokens.npz#3 of a one-robot file",
        6,
        lambda f: ["detokenize", f.tokens + "#3", "--out", f.root + "/r.xml"],
        ("index 3", "1 robot"),
    ),
    Case(
        "view: design index out of range",
        6,
        lambda f: ["view", f.designs + "#7", "--html", f.root + "/v.html"],
        ("index 7",),
    ),
    Case(
        "generate: unknown space",
        6,
        lambda f: ["generate", "--space", "cheetah", "--designs", "1", "--out", f.root + "/g1"],
        ("cheetah", "viperx"),
    ),
    Case("rollout: unknown backend", 6, lambda f: ["rollout", "--n", "1", "--backend", "bullet"], ("bullet", "warp")),
    Case("validate: unknown reward", 6, lambda f: [*V, f.designs, "--motion", "toss", "--reward", "speed"], ("speed",)),
    Case("motions --name nope", 6, lambda f: ["motions", "--name", "nope", "--out", f.root + "/m.npz"], ("nope",)),
    # -- 8: outputs written safely: through links, never over a socket
    Case(
        "tokenize --out through a symlink writes its target",
        8,
        lambda f: ["tokenize", f.designs, "--out", f.link],
        ok=True,
        check=_written_through("link", "link_target"),
    ),
    Case(
        "motions --out through a dangling symlink creates its target",
        8,
        lambda f: ["motions", "--name", "toss", "--out", f.dangling],
        ok=True,
        check=_written_through("dangling", "dangling_target"),
    ),
    Case(
        "validate --json onto a socket is refused",
        8,
        lambda f: [*V, f.designs + "#0", "--motion", "toss", "--json", f.socket],
        ("--json", "sock", "socket"),
    ),
    Case(
        "view --html onto a socket is refused",
        8,
        lambda f: ["view", f.designs, "--html", f.socket],
        ("--html", "socket"),
    ),
    # -- 9: '-' is stdout: a folder cannot go there, and two outputs cannot share it
    Case(
        "rollout --out - (a folder) is refused",
        9,
        lambda f: ["rollout", "--n", "1", "--out", "-"],
        ("--out -", "folder"),
    ),
    Case(
        "validate --json - with --episode - is refused",
        9,
        lambda f: [*V, f.designs + "#0", "--motion", "toss", "--json", "-", "--episode", "-"],
        ("--json", "--episode", "stdout"),
    ),
    Case(
        "detokenize --out - with --space is refused",
        9,
        lambda f: ["detokenize", f.tokens, "--out", "-", "--space", "viperx"],
        ("--space", "--out"),
    ),
    # -- 10: tt designs removes and overwrites only its own files
    Case(
        "designs --out over a user's viperx_0001.xml",
        10,
        lambda f: ["designs", "--n", "3", "--out", f.user_designs],
        ("--out", "viperx_0001.xml", "no earlier `tt designs` run"),
        check=_user_designs_kept,
    ),
    Case(
        "designs --out beside a user's aloha_0007.xml",
        10,
        lambda f: ["designs", "--n", "1", "--out", f.user_designs],
        ok=True,
        check=_user_designs_kept,
    ),
    # -- 14: a flag that does not apply to the method or mode is refused, naming both
    Case(
        "optimize --config critic_checkpoint with --method cmaes",
        14,
        lambda f: ["optimize", "--motion", "toss", "--config", f"critic_checkpoint={f.ckpt_nokey}"],
        ("critic_checkpoint", "popsize"),
    ),
    Case(
        "optimize --config samples with --method random",
        14,
        lambda f: ["optimize", "--motion", "toss", "--method", "random", "--config", "samples=4"],
        ("samples", "valid keys: none"),
    ),
    Case(
        "optimize --num-steps with --method random",
        14,
        lambda f: ["optimize", "--motion", "toss", "--method", "random", "--num-steps", "5"],
        ("--num-steps", "--method random"),
    ),
    Case(
        "optimize --config popsize with --method zeroth",
        14,
        lambda f: ["optimize", "--motion", "toss", "--method", "zeroth", "--config", "popsize=4"],
        ("popsize", "samples"),
    ),
    Case(
        "validate --device with --controller ik",
        14,
        lambda f: [*V, f.designs + "#0", "--motion", "toss", "--device", "cpu"],
        ("--device", "--controller ik"),
    ),
    Case(
        "detokenize --project without --space",
        14,
        lambda f: ["detokenize", f.tokens, "--out", f.root + "/r.xml", "--project"],
        ("--project", "--space"),
    ),
    Case("motions --out without --name", 14, lambda f: ["motions", "--out", f.root + "/m.npz"], ("--out", "--name")),
    Case(
        "rollout --n with --design", 14, lambda f: ["rollout", "--design", f.designs, "--n", "3"], ("--n", "--design")
    ),
    Case(
        "train --config online.designs with --data",
        14,
        lambda f: ["train", "--data", f.episodes, "--config", "online.designs=8", "--out", f.root + "/r14"],
        ("--data", "[online]"),
    ),
    # -- 15: messages name flags and files, never Python names (`outcome` checks every case for them)
    Case(
        "generate --config bias=nope lists the biases",
        15,
        lambda f: ["generate", "--designs", "1", "--config", "bias=nope", "--out", f.root + "/g15"],
        ("bias", "cmaes"),
    ),
    Case(
        "generate --seed 2**32 names the flag",
        15,
        lambda f: ["generate", "--designs", "1", "--seed", str(2**32), "--out", f.root + "/g15"],
        ("--seed",),
    ),
    Case(
        "generate --config action_noise=nan names the key",
        15,
        lambda f: ["generate", "--designs", "1", "--config", "action_noise=nan", "--out", f.root + "/g15"],
        ("action_noise",),
    ),
    Case(
        "train --online --config online.action_noise=nan names the key",
        15,
        lambda f: ["train", "--online", "--config", "online.action_noise=nan", "--out", f.root + "/r15"],
        ("action_noise",),
    ),
    Case("motions --arms 3 names the flag", 15, lambda f: ["motions", "--arms", "3"], ("--arms", "1 or 2")),
    Case(
        "train --init of another size names --size",
        15,
        lambda f: ["train", "--data", f.episodes, "--init", f.trained, "--size", "mini", "--out", f.root + "/r15"],
        ("--init", "--size tiny", "--size mini"),
    ),
    Case(
        "optimize: a truncated critic_checkpoint names the file",
        15,
        lambda f: [
            "optimize",
            "--motion",
            "toss",
            "--method",
            "zeroth",
            "--config",
            f"critic_checkpoint={f.ckpt_truncated}",
        ],
        ("ckpt_truncated.pt",),
    ),
    Case(
        "optimize: a critic_checkpoint of another space",
        15,
        lambda f: [
            "optimize",
            "--space",
            "aloha",
            "--motion",
            "toss",
            "--method",
            "zeroth",
            "--config",
            f"critic_checkpoint={_shipped_critic()}",
        ],
        ("'aloha'",),
    ),
    Case(
        "train: random bytes as --init are not called pickled data",
        15,
        lambda f: ["train", "--data", f.episodes, "--init", f.ckpt_random, "--out", f.root + "/r15"],
        ("ckpt_random.pt", "no file tt wrote"),
        check=lambda f, out: "said to hold pickled data" if "pickled data)" in out or "Python objects" in out else None,
    ),
    Case(
        "train selection.designs over a damaged selection.json",
        15,
        lambda f: ["train", "--data", f.episodes, "--config", "selection.designs=3", "--out", f.run_sel_json],
        ("selection.json", "not valid JSON"),
    ),
    Case(
        "train selection.designs over a damaged selection.csv",
        15,
        lambda f: ["train", "--data", f.episodes, "--config", "selection.designs=3", "--out", f.run_sel_csv],
        ("selection.csv", "not text"),
    ),
    Case(
        "validate --episode: the tt view hint is shell-quoted",
        15,
        lambda f: [*V, f.designs + "#0", "--motion", "toss", "--episode", f.spaced + "/ep.npz"],
        ok=True,
        check=lambda f, out: (
            None if f"tt view '{f.spaced}/ep.npz'" in out else "the printed `tt view` command is not shell-quoted"
        ),
    ),
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
    internal = [w for w in INTERNAL_NAMES if any(w in e for e in errors)]
    if internal:
        return Outcome(case, "misleading", code, out, f"the error names Python internals: {internal}")
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
        noisy = TokenBatch(
            {k: (v + rng.normal(0, sigma, v.shape)).astype(np.float32) for k, v in clean.values.items()},
            clean.ids,
            clean.mask,
        )
        yield from detokenize(norm.denormalize(noisy, detect_padding=True))


# ------------------------------------------------------------------ scenarios (issue 50, round two)
@dataclass
class Scenario:
    """A bad input a table row cannot hold: run(files, work) -> (kind, why), kind as `Outcome`'s
    (clear | ok | traceback | silent | misleading | loss); work: a folder of its own."""

    name: str
    cls: int
    run: Callable[[SimpleNamespace, Path], tuple[str, str]]


def _cli(args: list, cwd: Path | None = None) -> tuple[int, str, str]:
    """The real CLI in process: (exit code, stdout, stderr)."""
    import contextlib

    from typer.testing import CliRunner

    from tt.cli import app

    with contextlib.chdir(cwd) if cwd is not None else contextlib.nullcontext():
        res = CliRunner().invoke(app, [str(a) for a in args])
    out, err = res.stdout, res.stderr if res.stderr_bytes is not None else ""
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        err += f"\nTraceback (uncaught): {type(res.exception).__name__}: {res.exception}"
    return res.exit_code, out, err


def _error(code: int, out: str, err: str, *names: str) -> tuple[str, str]:
    """How a refusal went: clear when it exits non-zero with one error line naming `names`."""
    text = out + err
    if "Traceback" in text or "internal error" in text:
        return "traceback", text[-300:]
    if code == 0:
        return "silent", "exit 0 for a bad input"
    errors = [line for line in text.splitlines() if line.startswith("error: ")]
    if len(set(errors)) != 1:
        return "misleading", f"{len(set(errors))} distinct error lines: {text[-300:]}"
    missing = [n for n in names if n not in errors[0]]
    internal = [w for w in INTERNAL_NAMES if w in errors[0]]
    if missing or internal:
        return "misleading", f"the error {errors[0]!r} does not name {missing}" if missing else f"names {internal}"
    return "clear", ""


class _Quota:
    """A disk with `free` bytes left for files under `folder`: while active (a context), every
    file opened for writing there (``open``, ``io.open``, ``os.fdopen``) fails its writes with
    ENOSPC once the folder's new bytes pass `free`, as a full disk's do."""

    def __init__(self, folder: Path, free: int):
        self.folder, self.free, self.used = str(Path(folder).resolve()), free, 0

    def _inside(self, file) -> bool:
        import os

        try:
            path = os.readlink(f"/proc/self/fd/{file}") if isinstance(file, int) else os.path.realpath(file)
        except (OSError, TypeError):
            return False
        return str(path).startswith(self.folder + os.sep)

    def __enter__(self):
        import builtins
        import io
        from unittest import mock

        real = io.open
        quota = self

        class Full:
            def __init__(self, f):
                self._f = f

            def write(self, data):
                import errno
                import os

                quota.used += len(data)
                if quota.used > quota.free:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                return self._f.write(data)

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                self._f.close()

            def __getattr__(self, name):
                return getattr(self._f, name)

        def opener(file, mode="r", *args, **kwargs):
            f = real(file, mode, *args, **kwargs)
            return Full(f) if any(c in mode for c in "wax+") and self._inside(file) else f

        self._patches = [mock.patch("io.open", opener), mock.patch.object(builtins, "open", opener)]
        for p in self._patches:
            p.start()
        return self

    def __exit__(self, *exc):
        for p in self._patches:
            p.stop()


def _files_of(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()} if folder.is_dir() else {}


def _full_disk_html(files, work: Path) -> tuple[str, str]:
    """A full disk while tt view overwrites an existing --html file: the old page stays whole,
    no temporary file is left, and the error names the file."""
    page = work / "page.html"
    page.write_text("the earlier page")
    with _Quota(work, 1000):
        code, out, err = _cli(["view", files.designs, "--html", page])
    if page.read_text() != "the earlier page":
        return "loss", f"the earlier {page.name} was destroyed ({page.stat().st_size} bytes left)"
    if sorted(p.name for p in work.iterdir()) != ["page.html"]:
        return "loss", f"files left beside it: {sorted(p.name for p in work.iterdir())}"
    return _error(code, out, err, "No space left", str(page))


def _full_disk_designs(files, work: Path) -> tuple[str, str]:
    """A full disk in the middle of `tt designs` over an earlier run's folder: the folder stays
    as the earlier run left it (no half set, no 0-byte file), and the error names a file."""
    folder = work / "designs"
    _cli(["designs", "--n", "3", "--out", folder])
    before = _files_of(folder)
    size = len(before["viperx_0000.xml"])
    with _Quota(folder, int(2.5 * size)):
        code, out, err = _cli(["designs", "--n", "6", "--seed", "1", "--out", folder])
    after = _files_of(folder)
    if after != before or sorted(p.name for p in folder.iterdir()) != sorted(before):
        changed = sorted(set(after) ^ set(before)) + sorted(k for k in before if k in after and after[k] != before[k])
        return "loss", f"the folder changed: {changed[:6]} (of {len(after)} files)"
    return _error(code, out, err, "No space left", str(folder))


def _fifo_output(files, work: Path) -> tuple[str, str]:
    """--out onto a named pipe writes into the pipe (a reader gets the file) and leaves it a pipe."""
    import os
    import stat
    import threading

    fifo = work / "out.fifo"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(open(fifo, "rb").read()), daemon=True)
    reader.start()
    code, out, err = _cli(["motions", "--name", "toss", "--out", fifo])
    reader.join(30)
    if reader.is_alive() and stat.S_ISFIFO(os.stat(fifo).st_mode):
        open(fifo, "wb").close()  # release the reader
    if not stat.S_ISFIFO(os.lstat(fifo).st_mode):
        return "loss", "the named pipe was replaced by a regular file"
    if code != 0:
        return "misleading", f"exit {code}: {(out + err)[-300:]}"
    return ("ok", "") if got and got[0].startswith(b"PK") else ("silent", "the reader got no .npz")


def _stdout_outputs(files, work: Path) -> tuple[str, str]:
    """``-`` is stdout: stdout holds the output alone (the table goes to stderr) and no file
    named ``-`` appears."""
    cases = [
        ("validate --json -", [*V, files.designs + "#0", "--motion", "toss", "--json", "-"], "json"),
        (
            "optimize --json -",
            ["optimize", "--motion", "toss", "--method", "random", "--budget", "2", "--json", "-"],
            "json",
        ),
        (
            "predict --json -",
            ["predict", "--design", files.designs + "#0", "--motion", "toss", "--device", "cpu", "--json", "-"],
            "json",
        ),
        ("motions --out -", ["motions", "--name", "toss", "--out", "-"], "npz"),
        ("view --html -", ["view", files.designs + "#0", "--html", "-"], "html"),
    ]
    for name, args, kind in cases:
        code, out, err = _cli(args, cwd=work)
        if code != 0:
            return "misleading", f"{name}: exit {code}: {(out + err)[-300:]}"
        if (work / "-").exists():
            return "silent", f"{name} wrote a file named -"
        if kind == "json":
            try:
                json.loads(out)
            except ValueError:
                return "silent", f"{name}: stdout is not the JSON alone: {out[:120]!r}"
        elif kind == "npz" and not out.encode("utf-8", "surrogateescape").startswith(b"PK"):
            return "silent", f"{name}: stdout is not the .npz"
        elif kind == "html" and not out.lstrip().lower().startswith("<!doctype html"):
            return "silent", f"{name}: stdout is not the HTML alone: {out[:80]!r}"
    return "ok", ""


def _train(files, out: Path, steps: int, *extra, data: str | None = None) -> list:
    return [
        "train",
        "--data",
        data or files.episodes,
        "--size",
        "tiny",
        "--batch-size",
        "4",
        "--device",
        "cpu",
        "--steps",
        str(steps),
        "--config",
        "checkpoint_every=2",
        "--out",
        out,
        *extra,
    ]


def _no_resume_empties(files, work: Path) -> tuple[str, str]:
    """--no-resume over a finished run (step 4) empties it: the new run's step 2 is its only
    checkpoint, and a later resume continues from that step, not the old run's."""
    from tt.dit.checkpoint import list_checkpoints, load_checkpoint

    run = work / "run"
    code, out, err = _cli(_train(files, run, 4))
    if code:
        return "misleading", (out + err)[-300:]
    code, out, err = _cli(_train(files, run, 2, "--no-resume"))
    if code:
        return "misleading", (out + err)[-300:]
    names = [p.name for p in list_checkpoints(run)]
    if names != ["step_0000002.pt"]:
        return "loss", f"the earlier run's checkpoints are left beside the new one: {names}"
    code, out, err = _cli(_train(files, run, 3))
    state = load_checkpoint(list_checkpoints(run)[-1])
    if code or state["step"] != 3 or len(state["losses"]) != 3:
        return "loss", f"the resume did not continue the new run (step {state['step']}, {len(state['losses'])} losses)"
    return "ok", ""


def _two_writers(files, work: Path) -> tuple[str, str]:
    """A second `tt train` on a run folder another process writes is refused, before it
    touches the folder (its checkpoints stay)."""
    from tt.dit.checkpoint import list_checkpoints
    from tt.tokens.lock import DatasetLock

    run = work / "run"
    _cli(_train(files, run, 2))
    before = [p.name for p in list_checkpoints(run)]
    with DatasetLock(run):  # the first writer
        code, out, err = _cli(_train(files, run, 2, "--no-resume"))
    if [p.name for p in list_checkpoints(run)] != before:
        return (
            "loss",
            f"the second writer changed the run's checkpoints: {before} -> {[p.name for p in list_checkpoints(run)]}",
        )
    return _error(code, out, err, str(run), "being written")


def _init_on_a_run(files, work: Path) -> tuple[str, str]:
    """--init on a run folder that has checkpoints (which a resume would use instead) is refused."""
    run = work / "run"
    _cli(_train(files, run, 2))
    code, out, err = _cli(_train(files, run, 4, "--init", files.trained))
    return _error(code, out, err, "--init", str(run), "--no-resume")


def _regenerated_dataset(files, work: Path) -> tuple[str, str]:
    """A dataset regenerated at the same path with another --seed is refused on resume."""
    from dataclasses import replace

    from tt.generate import GenerateConfig, generate
    from tt.tokens.store import read_root

    data = work / "ds"
    shutil.copytree(files.dataset, data)
    run = work / "run"
    code, out, err = _cli(_train(files, run, 1, "--batch-size", "2", data=str(data)))
    if code:
        return "misleading", (out + err)[-300:]
    config = GenerateConfig.from_dict(read_root(data)["config"])
    shutil.rmtree(data)
    generate(replace(config, seed=config.seed + 1), data, device="cpu", progress=False)
    code, out, err = _cli(_train(files, run, 2, "--batch-size", "2", data=str(data)))
    return _error(code, out, err, "--data", "--seed 0 then, 1 now")


def _rewritten_episode_file(files, work: Path) -> tuple[str, str]:
    """An episode token file rewritten with other episodes at the same path is refused on resume."""
    from tt.dit.toy import toy_episodes

    data = work / "episodes.npz"
    shutil.copy(files.episodes, data)
    run = work / "run"
    _cli(_train(files, run, 1, data=str(data)))
    toy_episodes(episodes=6, steps=12, seed=1).save(data)
    code, out, err = _cli(_train(files, run, 2, data=str(data)))
    return _error(code, out, err, "--data", "content changed")


def _all_dropped(files, work: Path) -> tuple[str, str]:
    """A complete dataset whose episodes --min-steps all dropped says so (not "run tt generate first")."""
    from tt.generate import GenerateConfig, generate

    data = work / "ds"
    generate(
        GenerateConfig(
            space="viperx",
            designs=1,
            episodes_per_design=1,
            designs_per_shard=1,
            min_steps=100_000,
            max_motion_steps=None,
        ),
        data,
        device="cpu",
        progress=False,
    )
    code, out, err = _cli(_train(files, work / "run", 1, data=str(data)))
    kind, why = _error(code, out, err, "complete", "min_steps=100000")
    if kind == "clear" and "first" in out + err:
        return "misleading", "it says to run `tt generate` first"
    return kind, why


def _online_resume_message(files, work: Path) -> tuple[str, str]:
    """Resuming an online run with other online settings names the flags, not two OnlineConfig dicts."""
    from tt.dit.online import OnlineConfig
    from tt.dit.train import TrainConfig, check_same_run

    stored = TrainConfig(online=OnlineConfig(designs=64), out=str(work)).to_dict()
    try:
        check_same_run(stored, TrainConfig(online=OnlineConfig(designs=32), out=str(work)), work)
    except ValueError as e:
        text = str(e)
        if "online.designs" not in text or "{" in text or any(w in text for w in INTERNAL_NAMES):
            return "misleading", text
        return "clear", ""
    return "silent", "resumed with another online.designs"


def _api_generate_messages(files, work: Path) -> tuple[str, str]:
    """tt.api.generate_dataset's bad arguments, which no CLI check sees first, are refused
    before any folder is made, naming the flag and the keyword argument ("--designs
    (designs=)"), never a GenerateConfig field."""
    from tt.api import generate_dataset
    from tt.kernels.errors import TTError

    cases = [
        ({"designs": 0}, "--designs (designs=)"),
        ({"episodes_per_design": 0}, "--episodes-per-design (episodes_per_design=)"),
        ({"designs_per_shard": 0}, "designs_per_shard="),
        ({"min_steps": 0}, "min_steps="),
        ({"seed": 2**32}, "--seed (seed=)"),
        ({"bias": "nope"}, "bias="),
        ({"action_noise": float("nan")}, "action_noise="),
        ({"select": 0}, "select="),
        ({"uniform_share": 0.5}, "uniform_share="),
    ]
    out = work / "g"
    for given, named in cases:
        args = {"space": "viperx", "designs": 4, **given}
        try:
            generate_dataset(args.pop("space"), args.pop("designs"), out, progress=False, **args)
        except TTError as e:
            if named not in str(e) or any(w in str(e) for w in INTERNAL_NAMES):
                return "misleading", f"{given}: {e}"
            continue
        return "silent", f"generate_dataset accepted {given}"
    return ("silent", f"{out} was made for refused arguments") if out.exists() else ("clear", "")


def _serve_with_time(files, work: Path) -> tuple[str, str]:
    """--time with --serve alone (no HTML to open paused) is refused, naming both."""
    from tt.viz.cli import ViewError, view_cmd

    try:
        result = view_cmd(files.designs, serve=True, time=1.0, block=False, echo=lambda text: None)
    except ViewError as e:
        return ("clear", "") if "--time" in str(e) and "--html" in str(e) else ("misleading", str(e))
    from tt.viz.live import close_visualizer

    close_visualizer(result.visualizer)
    return "silent", "--time ignored by --serve"


def _short_motions_predicted(files, work: Path) -> tuple[str, str]:
    """tt predict on motions of 1, 2 and 3 frames (shorter than the model's 8-step window)
    scores their own steps, as tt validate does: through the CLI, no prediction counts more
    steps than its motion has, and survival means all of them counted; with the reward's
    termination threshold lifted, predict counts every step of the motion, as many as
    validate counts of an episode the rollout ran to the end."""
    from dataclasses import replace

    import torch

    from tt.api import predict_checkpoint
    from tt.baselines.evaluate import evaluate_designs
    from tt.dit.checkpoint import load_model
    from tt.guidance.predicted import CRITIC_DDIM_STEPS, predict_designs
    from tt.sim.designs import load_designs
    from tt.sim.motions import for_space, load_motion_file, save_npz
    from tt.sim.motions.base import Motion
    from tt.sim.rewards import RewardInputs, get_reward, metrics

    full = load_motion_file(files.motion, place=False)
    paths = []
    for T in (1, 2, 3):
        paths.append(work / f"frames_{T}.npz")
        save_npz(Motion(f"frames_{T}", full.pos[:T], full.quat[:T], full.dt), paths[-1])
    motion_args = [a for p in paths for a in ("--motion", p)]
    predicted, validated = work / "predicted.json", work / "validated.json"
    for args, out in (
        (["predict", "--design", files.designs, "--device", "cpu"], predicted),
        ([*V, files.designs], validated),
    ):
        code, text, err = _cli([*args, *motion_args, "--json", out])
        if code:
            return "misleading", f"{args[0]}: exit {code}: {(text + err)[-300:]}"
    frames = {f"frames_{T}": T for T in (1, 2, 3)}
    for p in json.loads(predicted.read_text())["predictions"]:
        T, m = frames[p["motion"]], p["metrics"]
        if m["length"] > T or (m["survival"] == 1.0) != (m["length"] == T):
            return "silent", (
                f"tt predict scored {m['length']:g} steps (survival {m['survival']:g}) of design "
                f"#{p['design']} on the {T}-frame motion {p['motion']}"
            )
    # Nothing terminating: both count every step of the motion, and only those.
    designs = load_designs(files.designs)
    motions = for_space([load_motion_file(p) for p in paths], "viperx")
    cfg = replace(get_reward("tracking", "viperx"), threshold=1e6)
    trained = load_model(predict_checkpoint("viperx"), device="cpu")
    pred = predict_designs(trained, designs, motions, cfg, num_steps=CRITIC_DDIM_STEPS).metrics["length"]
    ep = evaluate_designs(designs, motions, "tracking", device="cpu").episode
    steps = torch.tensor([m.steps for m in motions])[ep.motion_index.cpu()]
    sim = metrics(RewardInputs.from_episode(ep, motion_steps=steps.to(ep.ee_pos.device)), cfg)["length"]
    sim = sim.cpu().numpy().reshape(len(designs), len(motions))
    ran = ep.alive.sum(1).cpu().numpy().reshape(len(designs), len(motions)) == np.array([m.steps for m in motions])
    if not ran.any() or not (pred == np.array([m.steps for m in motions])).all() or not (pred == sim)[ran].all():
        return "silent", (
            f"with no termination tt predict counts {pred.tolist()} steps of the {[m.steps for m in motions]}, "
            f"tt validate {sim.tolist()} (episodes that ran every step: {ran.tolist()})"
        )
    return "ok", ""


def _damaged_dataset_root(files, work: Path) -> tuple[str, str]:
    """tt generate over an interrupted dataset whose zarr.json is damaged but whose shards are
    intact: other arguments are refused, naming the file and the flag; the same command says
    what it repaired, naming the file, rebuilds the root and resumes to the dataset an
    uninterrupted run writes (episode digests, shard manifests and root alike)."""
    from tt.tokens.store import TokenStore, shard_dirs

    args = [
        "generate",
        "--designs",
        "2",
        "--episodes-per-design",
        "1",
        "--config",
        "designs_per_shard=1",
        "--config",
        "min_steps=10",
        "--device",
        "cpu",
    ]
    whole, data = work / "whole", work / "ds"
    code, out, err = _cli([*args, "--out", whole])
    if code:
        return "misleading", f"exit {code}: {(out + err)[-300:]}"
    shutil.copytree(whole, data)
    shutil.rmtree(shard_dirs(data)[1])
    meta = data / "zarr.json"
    meta.write_bytes(b'{"zarr_format": 3, "node_type": "gr')  # a write cut short
    kind, why = _error(*_cli([*args, "--seed", "1", "--out", data]), str(meta), "damaged", "--seed")
    if kind != "clear":
        return kind, f"with another --seed: {why}"
    code, out, err = _cli([*args, "--out", data])
    if code:
        return "misleading", f"the same command: exit {code}: {(out + err)[-300:]}"
    if f"{meta}, the dataset's root, is damaged" not in out + err or "rebuilt" not in out + err:
        return "misleading", f"the repair of {meta} is not reported: {(out + err)[-300:]}"
    a, b = shard_dirs(whole), shard_dirs(data)
    same = (
        TokenStore(whole, verify="full").episode_digests() == TokenStore(data, verify="full").episode_digests()
        and sorted(a) == sorted(b)
        and all((a[i] / "manifest.json").read_bytes() == (b[i] / "manifest.json").read_bytes() for i in a)
        and meta.read_bytes() == (whole / "zarr.json").read_bytes()
    )
    return ("ok", "") if same else ("silent", "the repaired dataset differs from the uninterrupted one")


def killed_generate_leaves_no_workers(work: Path) -> tuple[str, str]:
    """SIGKILL of ``tt generate --workers 2`` once both workers are writing shards: every
    process it started stops, and no shard is written after. (tests/test_kills.py runs it.)"""
    import os
    import signal
    import subprocess
    import sys
    import time

    sys.path.insert(0, str(Path(__file__).parent))
    from listening import children, running, wait_gone

    def descendants(pid: int) -> list[int]:
        found, todo = [], [pid]
        while todo:
            try:
                kids = children(todo.pop())
            except (FileNotFoundError, ProcessLookupError):
                continue
            found += kids
            todo += kids
        return found

    out = work / "ds"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tt.cli",
            "generate",
            "--designs",
            "40",
            "--episodes-per-design",
            "1",
            "--config",
            "designs_per_shard=1",
            "--config",
            "min_steps=10",
            "--workers",
            "2",
            "--device",
            "cpu",
            "--out",
            str(out),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=work,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
    )
    left: list[int] = []
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:  # both workers started and writing shards
            partial = out / ".partial"
            if len(descendants(proc.pid)) >= 3 and partial.is_dir() and any(partial.iterdir()):
                break
            time.sleep(0.2)
        if proc.poll() is not None:
            return "misleading", "tt generate ended before its workers were busy"
        family = descendants(proc.pid)
        if len(family) < 3:
            return "misleading", f"expected a queue server and two workers, found {family}"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        left = [p for p in family if not wait_gone(p, timeout=15)]
        if left:
            return "loss", f"processes {left} of the killed tt generate still run"
        shards = sorted(p.name for p in (out / "shards").iterdir()) if (out / "shards").is_dir() else []
        time.sleep(2.0)
        later = sorted(p.name for p in (out / "shards").iterdir()) if (out / "shards").is_dir() else []
        return ("loss", "shards were still written after the run was killed") if later != shards else ("ok", "")
    finally:
        proc.kill()
        for pid in left:
            if running(pid):
                os.kill(pid, signal.SIGKILL)


SCENARIOS: list[Scenario] = [
    Scenario("view --html over an existing page on a full disk", 8, _full_disk_html),
    Scenario("motions --out onto a named pipe", 8, _fifo_output),
    Scenario("validate, optimize, predict --json -; motions --out -; view --html -", 9, _stdout_outputs),
    Scenario("designs over an earlier run on a full disk", 10, _full_disk_designs),
    Scenario("train --no-resume over a finished run", 11, _no_resume_empties),
    Scenario("train: two writers on one run folder", 11, _two_writers),
    Scenario("train --init on a run that has checkpoints", 11, _init_on_a_run),
    Scenario("train resume on a dataset regenerated with another --seed", 12, _regenerated_dataset),
    Scenario("train resume on a rewritten episode file", 12, _rewritten_episode_file),
    Scenario(
        "generate --workers 2 killed with SIGKILL", 13, lambda files, work: killed_generate_leaves_no_workers(work)
    ),
    Scenario("view --serve --time", 14, _serve_with_time),
    Scenario("train on a dataset whose episodes --min-steps all dropped", 15, _all_dropped),
    Scenario("train: resume online with another online.designs", 15, _online_resume_message),
    Scenario("tt.api.generate_dataset: bad arguments name the flag and the keyword", 15, _api_generate_messages),
    Scenario(
        "predict on motions of 1, 2 and 3 frames counts their steps, as validate does", 16, _short_motions_predicted
    ),
    Scenario("generate over a dataset whose zarr.json is damaged, its shards intact", 17, _damaged_dataset_root),
]
