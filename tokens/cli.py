"""The ``tt tokenize`` and ``tt detokenize`` commands as plain functions returning text.

`tt.cli` wires them to typer; a failure raises `TokenCommandError` with the message to
print (missing file, a model RoboTokens cannot hold, a robot MuJoCo will not load).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import mujoco

from tt.kernels.errors import TTError
from tt.kernels.files import write_text
from tt.tokens.batch import TokenBatch
from tt.tokens.detokenize import DetokenizeConfig, detokenize
from tt.tokens.schema import EMBODIMENT_TYPES, SCHEMA_VERSION
from tt.tokens.tokenize import TokenizeError, TokenizeWarning, tokenize_models


class TokenCommandError(TTError):
    """What went wrong, phrased for the command line."""


def _load_robots(spec: str) -> list[tuple[str, str, mujoco.MjModel]]:
    """(name, MJCF text, model) of every robot in an MJCF / URDF file or a design file
    (designs.json, or one design of it: designs.json#i)."""
    base, sep, index = spec.rpartition("#")
    path = Path(base if sep and base.endswith(".json") else spec)
    if not path.exists():
        raise TokenCommandError(f"{path} does not exist")
    if path.is_dir():
        raise TokenCommandError(f"{path} is a folder; give an MJCF or URDF file, or a designs.json")
    if path.stat().st_size == 0:
        raise TokenCommandError(f"{path} is empty (0 bytes)")
    if path.suffix == ".json":
        from tt.sim.backends.base import resolve_designs
        from tt.sim.designs import DesignError, load_designs

        try:
            designs = load_designs(spec)
            robots = resolve_designs(designs, who=f"tokenizing {path}", one_space=False)
        except (DesignError, ValueError) as e:
            raise TokenCommandError(str(e)) from None
        numbers = [int(index)] if path != Path(spec) else range(len(designs))  # load_designs checked the index
        return [
            (f"{d.space}#{i}", text, model) for i, d, text, model in zip(numbers, designs, robots.mjcf, robots.models)
        ]
    try:
        # From the path, so meshes and includes resolve next to the file.
        model = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as e:
        raise TokenCommandError(f"MuJoCo cannot load {path}: {e}") from None
    return [(path.name, path.read_text(errors="replace"), model)]


def tokenize_cmd(path: str, as_json: bool = False, out: str | None = None) -> str:
    """``tt tokenize FILE.xml|designs.json [--json] [--out tokens.npz]``.

    Tokenizes every robot of the file; returns per robot the number of tokens of each type,
    the total and the MJCF text size in characters, as a table or as JSON. `out` saves the
    tokens (with the schema version) for ``tt detokenize``.
    """
    robots = _load_robots(str(path))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", TokenizeWarning)
        try:
            emb = tokenize_models([m for _, _, m in robots])
        except TokenizeError as e:
            raise TokenCommandError(str(e)) from None
    counts = emb.tokens.counts()
    rows = []
    for i, (name, text, _) in enumerate(robots):
        row = {"robot": name, **{t: int(counts[t][i]) if t in counts else 0 for t in EMBODIMENT_TYPES}}
        row["total"] = sum(row[t] for t in EMBODIMENT_TYPES)
        row["mjcf_chars"] = len(text)
        rows.append(row)
    notes = sorted({str(w.message) for w in caught if issubclass(w.category, TokenizeWarning)})
    if out is not None:
        emb.tokens.save(out)
    if as_json:
        return json.dumps({"schema_version": SCHEMA_VERSION, "robots": rows, "notes": notes, "saved": out}, indent=1)
    cols = ["robot", *EMBODIMENT_TYPES, "total", "mjcf_chars"]
    widths = [max(len(c), *(len(str(r[c])) for r in rows)) for c in cols]
    lines = ["  ".join(c.rjust(w) for c, w in zip(cols, widths))]
    lines += ["  ".join(str(r[c]).rjust(w) for c, w in zip(cols, widths)) for r in rows]
    lines += [f"note: {n}" for n in notes]
    if out is not None:
        lines.append(f"saved {len(rows)} robot(s) to {out} (RoboToken schema v{SCHEMA_VERSION})")
    return "\n".join(lines)


def detokenize_cmd(path: str, out: str, index: int = 0, space: str | None = None, project: bool = False) -> str:
    """``tt detokenize TOKENS.npz --out robot.xml [--index i] [--space viperx [--project]]``.

    Writes robot `index` of the token file as MJCF to `out` (also when MuJoCo refuses it,
    so it can be inspected, then raises with MuJoCo's reason). With `space`, also fits
    that design space's choices to the tokens and writes them to ``<out>.design.json``
    (`project`: the nearest design when no choice has the tokens' exact structure).
    """
    try:
        tokens = TokenBatch.load(path)
    except (FileNotFoundError, ValueError) as e:
        raise TokenCommandError(str(e)) from None
    if not 0 <= index < len(tokens):
        raise TokenCommandError(f"index {index} is out of range: {path} holds {len(tokens)} robot(s)")
    result = detokenize(tokens.select(index), DetokenizeConfig(model=Path(out).stem))[0]
    if result.xml:
        write_text(out, result.xml)
    if not result.ok:
        raise TokenCommandError(f"{result.error}" + (f" (MJCF written to {out})" if result.xml else ""))
    m = result.model
    lines = [
        f"wrote {out}: {m.nbody - 1} bodies, {m.njnt} joints, {m.nu} actuators, {m.neq} loop closures, "
        f"{len(result.xml)} characters"
    ]
    lines += [f"note: {n}" for n in result.notes]
    if space is not None:
        from tt.sim.designs import DesignError, get_space, save_designs
        from tt.tokens.design_fit import design_from_tokens

        try:
            sp = get_space(space)
        except DesignError as e:
            raise TokenCommandError(str(e)) from None
        fit = design_from_tokens(tokens, index, sp, max_distance=None if project else 0)
        if fit.design is None:
            raise TokenCommandError(
                f"no {space} design has this token structure (nearest: {fit.distance} binary attributes "
                "off); --project takes the nearest design"
            )
        design_path = str(Path(out).with_suffix("")) + ".design.json"
        save_designs([fit.design], design_path)
        lines.append(
            f"wrote {design_path}: {space} design, token residual {fit.residual:.2e} (RMS)"
            + (f", projected from a structure {fit.distance} binary attributes off" if fit.distance else "")
        )
    return "\n".join(lines)
