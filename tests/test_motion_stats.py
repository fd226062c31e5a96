"""Motion statistics against closed forms, and `tt motions --stats`."""

import math

import numpy as np
import pytest

from tt.sim.motions import Motion, motion_stats


def _line_with_turn(speed: float, steps: int = 101, dt: float = 0.02, turn_deg: float = 90.0) -> Motion:
    t = np.arange(steps) * dt
    pos = np.stack([speed * t, np.zeros_like(t), np.full_like(t, 0.3)], axis=-1)
    half = np.radians(turn_deg) * t / t[-1] / 2  # rotation about z growing to turn_deg
    quat = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], axis=-1)
    return Motion("line", pos, quat, dt)


def test_stats_of_a_straight_line_at_constant_speed():
    (s,) = motion_stats([_line_with_turn(2.0)])
    assert s.peak_speed == pytest.approx(2.0, rel=1e-9) and s.p95_speed == pytest.approx(2.0, rel=1e-9)
    assert s.peak_accel == pytest.approx(0.0, abs=1e-6)
    assert s.extent == pytest.approx(2.0 * 100 * 0.02, rel=1e-12)
    assert s.orn_range == pytest.approx(90.0, rel=1e-9)


def test_stats_of_a_sine_match_its_derivatives():
    """x = a sin(w t): peak speed a w, peak acceleration a w^2 (to the central difference's error)."""
    a, w, dt = 0.2, 2 * math.pi, 0.002
    t = np.arange(0, 2.0, dt)
    pos = np.stack([a * np.sin(w * t), 0 * t, 0 * t + 0.3], -1)
    quat = np.tile([1.0, 0, 0, 0], (t.size, 1))
    (s,) = motion_stats([Motion("sine", pos, quat, dt)])
    assert s.peak_speed == pytest.approx(a * w, rel=1e-4)
    assert s.peak_accel == pytest.approx(a * w * w, rel=1e-3)
    assert s.extent == pytest.approx(2 * a, rel=1e-4) and s.orn_range == 0.0


def test_two_arms_report_the_larger():
    one, two = _line_with_turn(1.0), _line_with_turn(3.0, turn_deg=30.0)
    both = Motion("both", np.concatenate([one.pos, two.pos], 1), np.concatenate([one.quat, two.quat], 1), one.dt)
    (s,) = motion_stats([both])
    assert s.arms == 2 and s.peak_speed == pytest.approx(3.0) and s.orn_range == pytest.approx(90.0)


def test_too_short_a_motion_is_refused():
    with pytest.raises(ValueError, match="at least 3"):
        motion_stats([Motion("short", np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)))])


def test_cli_stats_lists_every_skill(tt_cli):
    from tt.sim.motions import list_motions

    code, out = tt_cli(["motions", "--stats", "--arms", "1"])
    assert code == 0, out
    for info in list_motions(arms=1):
        assert info.name in out
    assert "peak speed (m/s)" in out and "bi_fling" not in out


def test_piped_table_keeps_whole_rows():
    """Piped (``tt motions | tee``), rich would fold each cell into 80 columns; each motion's
    row, its summary included, stays on one line."""
    from typer.testing import CliRunner

    from tt.cli import app
    from tt.sim.motions import list_motions

    res = CliRunner().invoke(app, ["motions", "--arms", "1"], env={"COLUMNS": None})
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    for info in list_motions(arms=1):
        row = [line for line in lines if f"│ {info.name} " in line]
        assert len(row) == 1 and info.summary in row[0], (info.name, row)
