"""checkpoints/recipes/*.toml reproduce the shipped checkpoints' training runs: the settings
`tt train --config RECIPE [--init ...]` builds are the ones each checkpoint records."""

from pathlib import Path

import pytest
import torch

from tt.cli import train_settings
from tt.dit.online import OnlineConfig
from tt.dit.train import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "checkpoints" / "recipes"

#: recipe -> (the shipped checkpoint it trains, the --init its command gives).
SHIPPED = {
    "viperx_mini.toml": ("viperx_mini.pt", None),
    "viperx_mini_robot.toml": ("viperx_mini_robot.pt", "viperx_mini.pt"),
    "viperx_mini_dynamics.toml": ("viperx_mini_dynamics.pt", None),
    "viperx-nominal_mini_dynamics.toml": ("viperx-nominal_mini_dynamics.pt", None),
    "aloha_mini_dynamics.toml": ("aloha_mini_dynamics.pt", None),
    "aloha_mini_robot.toml": ("aloha_mini_robot.pt", None),
    "quadruped_mini_dynamics.toml": ("quadruped_mini_dynamics.pt", None),
    "bimanual_mini_dynamics.toml": ("bimanual_mini_dynamics.pt", None),
    "bimanual_mini_robot.toml": ("bimanual_mini_robot.pt", None),
    "bimanual_mini_control.toml": ("bimanual_mini_control.pt", None),
    "quadruped_mini_robot.toml": ("quadruped_mini_robot.pt", None),
}

#: The recorded fields a recipe must reproduce (device, out and data paths aside).
FIELDS = (
    "task",
    "size",
    "steps",
    "batch_size",
    "lr",
    "warmup_steps",
    "checkpoint_every",
    "prediction",
    "time_ids",
    "anchor_track",
    "anchor_control",
    "known_command",
    "future_states",
    "dynamics_start",
    "robot_diffusion_steps",
    "control_diffusion_steps",
    "type_weights",
)
ONLINE = ("space", "designs", "motions", "refresh_every", "buffer", "absorbing", "select", "propose", "propose_steps")


def test_every_recipe_is_a_shipped_checkpoints():
    assert sorted(p.name for p in RECIPES.glob("*.toml")) == sorted(SHIPPED)


@pytest.mark.parametrize("recipe", sorted(SHIPPED))
def test_recipe_reproduces_the_checkpoints_run(recipe):
    target, init = SHIPPED[recipe]
    stored = torch.load(ROOT / "checkpoints" / target, map_location="cpu", weights_only=True)["train_config"]
    settings = train_settings([str(RECIPES / recipe)], ROOT / "checkpoints" / init if init else None)
    online = settings.pop("online")
    settings.pop("selection", None)
    config = TrainConfig(online=OnlineConfig(**online), **settings)
    for name in FIELDS:
        want = stored.get(name)
        if want is None and name in ("dynamics_start", "control_target_offset"):
            want = False if name == "dynamics_start" else 0  # older checkpoints record no value: the default
        assert getattr(config, name) == want, (recipe, name, getattr(config, name), want)
    for name in ONLINE:  # a field older than the checkpoint: its default
        want = stored["online"].get(name, getattr(OnlineConfig(), name))
        assert getattr(config.online, name) == want, (recipe, name)


def test_a_recipe_key_that_does_not_exist_is_refused(tmp_path):
    from tt.kernels.errors import TTError

    bad = tmp_path / "r.toml"
    bad.write_text('task = "robot"\nknown_comand = true\n')
    with pytest.raises(TTError, match="unknown key 'known_comand'; valid keys: .*known_command"):
        train_settings([str(bad)])
    with pytest.raises(TTError, match="unknown key online.desings; valid keys of \\[online\\]: space, designs"):
        train_settings(["online.desings=4"])
    with pytest.raises(TTError, match="steps = 'many' is not of type int"):
        train_settings(["steps=many"])
    assert train_settings(["steps=8", "online.select=4", "steps=9"], steps=None) == {
        "steps": 9,
        "online": {"select": 4},
    }
    assert train_settings(["steps=8"], steps=3)["steps"] == 3  # a flag wins
