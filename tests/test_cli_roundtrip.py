"""The CLI's outputs feed its inputs: every file tt writes designs to is read back by every
command that reads designs (`--design`, `tt view`, `tt tokenize`), and `tt designs --nominal`
writes the space's nominal design."""

import json

import numpy as np
import pytest

from tt.sim.designs import DesignError, get_space, load_designs
from tt.sim.motions import Motion, for_space, get_motion, save_npz

STEPS = 40  # a short toss: the oracle validates it in a few seconds


@pytest.fixture(scope="module")
def motion_file(tmp_path_factory):
    m = for_space([get_motion("toss", 100)], "viperx")[0]
    path = tmp_path_factory.mktemp("motion") / "toss_short.npz"
    save_npz(Motion(f"{m.name}[:{STEPS}]", m.pos[:STEPS], m.quat[:STEPS], m.dt), path)
    return path


@pytest.fixture(scope="module")
def optimized(tmp_path_factory, motion_file):
    """`tt optimize --json`'s file (the cheap random search)."""
    from typer.testing import CliRunner

    from tt.cli import app

    path = tmp_path_factory.mktemp("opt") / "best.json"
    res = CliRunner().invoke(
        app,
        [
            "optimize",
            "--space",
            "viperx",
            "--motion",
            str(motion_file),
            "--method",
            "random",
            "--budget",
            "4",
            "--seed",
            "3",
            "--json",
            str(path),
        ],
    )
    assert res.exit_code == 0, res.output
    return path


def test_validate_and_view_accept_optimize_json(optimized, motion_file, tmp_path, tt_cli):
    data = json.loads(optimized.read_text())
    best = get_space("viperx").from_dict(data["design"])
    assert load_designs(optimized) == [best] and load_designs(f"{optimized}#0") == [best]

    out = tmp_path / "validated.json"
    code, text = tt_cli(["validate", "--design", str(optimized), "--motion", str(motion_file), "--json", str(out)])
    assert code == 0, text
    validated = json.loads(out.read_text())
    assert validated["designs"] == [data["design"]]
    # the oracle run on the file's design gives what tt optimize reported for its winner
    for key in ("pos_err", "reward", "survival_pct"):
        assert validated["metrics"][0][key] == pytest.approx(data["validated"][key], rel=1e-6, nan_ok=True), key

    html = tmp_path / "best.html"
    code, text = tt_cli(["view", str(optimized), "--html", str(html)])
    assert code == 0, text
    assert html.stat().st_size > 10_000 and "<html" in html.read_text()[:2000].lower()


def test_every_design_file_tt_writes_is_read_back(optimized, motion_file, tmp_path, tt_cli):
    """`tt validate --json` (designs beside metrics), `tt detokenize --space` (OUT.design.json)
    and `tt demo`'s demo.json (designs by method) are design files too."""
    sp = get_space("viperx")
    nominal = sp.nominal()
    folder = tmp_path / "nominal"
    assert tt_cli(["designs", "--space", "viperx", "--nominal", "--out", str(folder)])[0] == 0

    # tt tokenize -> tt detokenize --space: the fitted design is read back as the nominal
    tokens = tmp_path / "t.npz"
    code, text = tt_cli(["tokenize", str(folder / "designs.json"), "--out", str(tokens)])
    assert code == 0, text
    code, text = tt_cli(["detokenize", str(tokens), "--out", str(tmp_path / "robot.xml"), "--space", "viperx"])
    assert code == 0, text
    (fitted,) = load_designs(tmp_path / "robot.design.json")
    assert fitted.discrete == nominal.discrete
    np.testing.assert_allclose(fitted.continuous, nominal.continuous, atol=1e-5)

    # tt demo's demo.json holds its winners by method, in its table's order
    other = sp.sample(1, 5)[0]
    demo = tmp_path / "demo.json"
    demo.write_text(
        json.dumps(
            {"space": "viperx", "rows": [], "designs": {"Random": sp.to_dict(other), "CMA-ES": sp.to_dict(nominal)}}
        )
    )
    assert load_designs(demo) == [other, nominal] and load_designs(f"{demo}#1") == [nominal]
    code, text = tt_cli(["tokenize", f"{demo}#1", "--json"])  # tokenize reads one design of a file too
    assert code == 0, text
    assert [r["robot"] for r in json.loads(text)["robots"]] == ["viperx#1"]

    # a JSON file with no designs in it is named, with the forms tt reads
    (tmp_path / "summary.json").write_text(json.dumps({"space_name": "viperx", "metrics": []}))
    with pytest.raises(DesignError, match=r"summary\.json holds no designs.*tt designs.*tt optimize --json"):
        load_designs(tmp_path / "summary.json")


def test_nominal_round_trips_through_validate(motion_file, tmp_path, tt_cli):
    from tt.baselines import evaluate_designs
    from tt.sim.motions import load_motion_file

    sp = get_space("viperx")
    folder = tmp_path / "nominal"
    code, text = tt_cli(["designs", "--space", "viperx", "--nominal", "--out", str(folder)])
    assert code == 0 and "nominal" in text, text
    assert sorted(p.name for p in folder.iterdir()) == ["designs.json", "viperx_0000.xml"]
    assert load_designs(folder / "designs.json") == [sp.nominal()]
    assert (folder / "viperx_0000.xml").read_text() == sp.to_mjcf(sp.nominal())

    out = tmp_path / "v.json"
    code, text = tt_cli(
        ["validate", "--design", f"{folder / 'designs.json'}#0", "--motion", str(motion_file), "--json", str(out)]
    )
    assert code == 0, text
    got = json.loads(out.read_text())["per_motion"]
    want = evaluate_designs([sp.nominal()], [load_motion_file(motion_file)], "tracking", backend="mujoco").metrics
    assert set(want) <= set(got)
    for key, value in want.items():
        np.testing.assert_allclose(
            np.asarray(got[key], dtype=float), np.asarray(value, dtype=float), rtol=1e-9, err_msg=key
        )


@pytest.mark.parametrize("space", ["aloha", "bimanual", "quadruped", "viperx-nominal"])
def test_nominal_of_every_space(space, tmp_path, tt_cli):
    code, text = tt_cli(["designs", "--space", space, "--nominal", "--out", str(tmp_path)])
    assert code == 0, text
    assert load_designs(tmp_path / "designs.json") == [get_space(space).nominal()]


@pytest.mark.parametrize("flag", [["--n", "3"], ["--seed", "2"]])
def test_nominal_refuses_sampling_flags(flag, tmp_path, tt_cli):
    code, text = tt_cli(["designs", "--nominal", *flag, "--out", str(tmp_path / "d")])
    assert code == 2 and "--nominal" in text and flag[0] in text, text
    assert not (tmp_path / "d").exists()


def test_validate_without_a_motion_runs_the_spaces_default(tmp_path, tt_cli):
    """As `tt rollout` and `tt.validate` do: the toss for the one-arm ViperX (the same numbers
    as --motion toss)."""
    folder = tmp_path / "nominal"
    assert tt_cli(["designs", "--space", "viperx", "--nominal", "--out", str(folder)])[0] == 0
    runs = {}
    for name, extra in (("default", []), ("toss", ["--motion", "toss"])):
        out = tmp_path / f"{name}.json"
        code, text = tt_cli(["validate", "--design", str(folder / "designs.json"), *extra, "--json", str(out)])
        assert code == 0, text
        runs[name] = json.loads(out.read_text())
    assert runs["default"] == runs["toss"]


def test_rollout_takes_the_space_of_its_design_file(tmp_path, tt_cli):
    """`tt rollout --design FILE` without --space rolls out the file's space (as validate and
    predict do); a --space that disagrees with the file is refused."""
    folder = tmp_path / "aloha"
    assert tt_cli(["designs", "--space", "aloha", "--nominal", "--out", str(folder)])[0] == 0
    code, text = tt_cli(["rollout", "--design", str(folder / "designs.json")])
    assert code == 0 and "bi_fling" in text and "1 world," in text, text
    code, text = tt_cli(["rollout", "--design", str(folder / "designs.json"), "--space", "viperx"])
    assert code != 0 and "are from ['aloha']" in text, text
