"""Target motions: the procedural skill library, motion files and SE(2) augmentation.

``get_motion("toss")`` is the canonical toss, ``get_motion("toss", seed=7)`` (or
``"toss:7"``) a variant; ``motion_set("train", arms=1)`` / ``motion_set("val", arms=1)``
are the fixed splits; ``load_motion_file(path)`` reads ``.npz`` files and UMI zarr stores.

Where things live: `base` (the `Motion` type, quaternion helpers), `script` (the smooth
keyframe builder skills are written in), `workspace` (where targets may go), `skills` (the
15 skills and the seed splits), `registry` (the library by name), `io` (files,
resampling, SE(2) augmentation, per-space placement), `stats` (speed and extent figures).
"""

from tt.sim.motions.base import MOTION_DT, MOTION_HZ, Motion, MotionError
from tt.sim.motions.io import (
    UMI_HZ,
    UMI_TOOL_QUAT,
    augment_motion,
    augment_se2,
    for_space,
    load_motion_file,
    load_npz,
    load_umi_zarr,
    place_at_base,
    recenter,
    resample,
    resample_motion,
    resolve_motion,
    save_npz,
    umi_episode_count,
)
from tt.sim.motions.registry import (
    DEFAULT_MOTIONS,
    SKILLS,
    MotionInfo,
    default_motion,
    get_motion,
    list_motions,
    motion_set,
)
from tt.sim.motions.skills import SPLITS, TRAIN_SEEDS, VAL_SEEDS, Skill, SkillParam, split_of
from tt.sim.motions.stats import MotionStats, motion_stats
from tt.sim.motions.workspace import (
    BIMANUAL,
    BIMANUAL_CENTER,
    BIMANUAL_MOUNT_Y,
    SINGLE_ARM,
    SINGLE_ARM_CENTER,
    Workspace,
    workspaces,
)

__all__ = [
    "DEFAULT_MOTIONS",
    "default_motion",
    "motion_stats",
    "BIMANUAL",
    "BIMANUAL_CENTER",
    "BIMANUAL_MOUNT_Y",
    "MOTION_DT",
    "MOTION_HZ",
    "MotionStats",
    "for_space",
    "Motion",
    "MotionError",
    "MotionInfo",
    "SINGLE_ARM",
    "SINGLE_ARM_CENTER",
    "SKILLS",
    "SPLITS",
    "Skill",
    "SkillParam",
    "TRAIN_SEEDS",
    "UMI_HZ",
    "UMI_TOOL_QUAT",
    "VAL_SEEDS",
    "Workspace",
    "augment_motion",
    "augment_se2",
    "get_motion",
    "list_motions",
    "load_motion_file",
    "load_npz",
    "load_umi_zarr",
    "motion_set",
    "place_at_base",
    "recenter",
    "resample",
    "resample_motion",
    "resolve_motion",
    "save_npz",
    "split_of",
    "umi_episode_count",
    "workspaces",
]
