"""The ``tt`` command line. Commands import their implementation lazily so ``--help`` is fast."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import List, Optional

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="tt: motion-conditioned robot co-design (design spaces, batched simulation, RoboTokens, DiT).",
)


def _fail(message: str) -> None:
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code=2)


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log at INFO level.")) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")


@app.command()
def designs(
    space: str = typer.Option("viperx", help="Design space: viperx, aloha, bimanual, quadruped."),
    n: int = typer.Option(8, help="Number of designs to sample."),
    seed: int = typer.Option(0, help="Random seed."),
    out: Path = typer.Option(Path("designs"), help="Output folder for MJCF files and designs.json."),
) -> None:
    """Sample designs of a space; write one MJCF file each and designs.json."""
    from tt.sim.designs import DesignError, get_space, save_designs

    try:
        sp = get_space(space)
        ds = sp.sample(n, seed)
    except (DesignError, ValueError) as e:
        _fail(str(e))
    out.mkdir(parents=True, exist_ok=True)
    for i, d in enumerate(ds):
        (out / f"{space}_{i:04d}.xml").write_text(sp.to_mjcf(d))
    save_designs(ds, out / "designs.json")
    typer.echo(f"wrote {len(ds)} {space} designs to {out}/ (designs.json + {len(ds)} MJCF files)")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
