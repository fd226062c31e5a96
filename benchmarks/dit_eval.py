"""Evaluation of a trained ViperX DiT: critic, generator and controller.

(a) Predicted vs simulated reward, as in the paper's "Predicted Reward Accuracy" figure:
    for held-out (validation) motions, the model generates candidate robots
    (motion-to-robot task, 100 DDIM steps) and predicts each one's tracking reward from
    its own predicted dynamics tokens (`tt.guidance.predicted.PredictedReward`, the
    (T / S)-scaled estimate Zeroth-Order ranks by); each candidate is decoded to the
    nearest ViperX design (what the optimizers return) and simulated on that motion
    (DiffIK, tracking reward of
    `tt.sim.rewards`). Reported: Pearson r (and Spearman) over all candidates, and
    a scatter plot.
(b) Validity and diversity of samples: motion-conditioned samples (those of (a)) and
    unconditional ones (the same query with the target-pose tokens masked out of
    attention: the model sees no motion). Share that decode to a loadable robot (the
    generic detokenizer's MJCF compiles in MuJoCo), that have a ViperX token structure
    exactly, and that project onto a ViperX design (nearest structure, continuous choices
    fitted), with the projection's distance; and the distribution of the designs' DoF count
    and mount against the training episodes'.
(c) The model as controller (`tt.dit.policies`, `ControllerConfig`'s defaults, Warp
    physics) on held-out ViperX designs (sampled with a seed no training shard used) x
    validation motions, against the MuJoCo + mink oracle on the same designs and motions:
    mean tracking reward as a share of the oracle's, the paper's tracking metrics, and
    the per-episode correlation.

(d) Predicted vs simulated reward on held-out episodes: held-out ViperX designs (a seed no
    training shard used) on the validation motions of (a). The model is given each design
    (its embodiment tokens, inpainted: `tt.guidance.predicted.design_query` and
    `tt.dit.sampling.sample(known=...)`) and predicts only its dynamics; the predicted
    tracking reward is compared with the simulated episode's. A second row applies the
    same 8-step estimator to the simulated end-effector poses: the correlation the
    estimator itself allows, so what is lost below it is the model's.

Every part's sizes are options (the CPU is shared; defaults take a few minutes each on a
free 2-core CPU). Each run rewrites the header and the sections of the parts it ran in
``benchmarks/results/dit_eval.md`` (other parts' sections are kept) and writes
``benchmarks/results/dit_eval_reward.png`` for (a) and ``dit_eval_heldout.png`` for (d)
(beside ``--out``). Prints one JSON line per result.

Usage: ``python benchmarks/dit_eval.py CHECKPOINT [--parts abcd] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

RESULTS = Path(__file__).parent / "results"
SPACE = "viperx"


def emit(**fields) -> dict:
    print(json.dumps({"bench": "dit_eval", **fields}), flush=True)
    return fields


def validation_motions(count: int):
    """`count` validation motions of different skills, spread over the split, placed for ViperX
    (`tt.ladder.validation_motions`)."""
    from tt.ladder import validation_motions as space_validation_motions

    return space_validation_motions(SPACE, count)


def cut(motions, steps: int | None):
    """Motions cut to their first `steps` control steps (None or 0: whole)."""
    from tt.sim.motions.base import Motion

    if not steps:
        return list(motions)
    return [
        Motion(m.name, m.pos[:steps], m.quat[:steps], m.dt, meta=dict(m.meta, cut=steps)) if m.steps > steps else m
        for m in motions
    ]


def pearson(x: np.ndarray, y: np.ndarray) -> float:
    if len(x) < 3 or np.std(x) == 0 or np.std(y) == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    from scipy.stats import rankdata

    return pearson(rankdata(x), rankdata(y))


def choices(space, design) -> dict[str, str]:
    """Discrete choices of a design by parameter name."""
    params = space.discrete_params(design.discrete)
    return {p.name: p.options[i] for p, i in zip(params, design.discrete)}


class Decoder:
    """Candidates' embodiment tokens -> per candidate (detokenized MjModel or None, ViperX design
    or None, structure distance): the design is the nearest one (`DesignDecoder` with
    ``max_distance=None``, what the optimizers return); distance 0 means the candidate had a
    ViperX token structure itself, -1 that decoding failed."""

    def __init__(self, space, top_k: int):
        from tt.guidance.zeroth import DesignDecoder
        from tt.tokens.design_fit import CandidateTable

        self.space = space
        t = time.perf_counter()
        self.decoder = DesignDecoder(space, CandidateTable(space), max_distance=None, top_k=top_k)
        emit(part="setup", what="candidate_table", seconds=time.perf_counter() - t, choices=len(self.decoder.table))

    def __call__(self, batch) -> list[tuple[object, object, int]]:
        from tt.tokens.detokenize import detokenize

        models = [r.model for r in detokenize(batch)]
        out = []
        for i in range(len(batch)):
            dec = self.decoder(batch, i)
            design, distance = dec.design, (dec.distance if dec.design is not None else -1)
            if design is not None:
                try:
                    self.space.model(design)  # the decoded design compiles
                except Exception:  # counts as not decoded, whatever broke
                    design, distance = None, -1
            out.append((models[i], design, distance))
        return out


def oracle_rewards(models, motion, failures: dict[str, int]) -> list[float | None]:
    """Tracking reward of each MjModel on `motion` under the oracle; None where it cannot run
    (no end-effector site, an actuator the DiffIK cannot command, ...), the reason counted in
    `failures`."""
    from tt.sim.rewards import RewardInputs, get_reward, reward
    from tt.sim.validate import oracle_rollout

    cfg = get_reward("tracking", SPACE)
    out = []
    for m in models:
        try:
            ep = oracle_rollout([m], [motion])
            out.append(float(reward(RewardInputs.from_episode(ep), cfg)[0]))
        except Exception as e:  # a generated robot may be outside what the oracle drives; counted, not scored
            why = re.sub(r"'[^']*'|\d+", "_", f"{type(e).__name__}: {e}")[:120]
            failures[why] = failures.get(why, 0) + 1
            out.append(None)
    return out


class NoMotion(torch.nn.Module):
    """The model with its target-pose tokens masked out of attention: an unconditional sampler."""

    def __init__(self, model):
        super().__init__()
        self.model = model
        self.layout = model.layout
        hide = torch.cat([torch.full((s.length,), s.role.value != "condition") for s in model.layout.specs])
        self.register_buffer("visible", hide, persistent=False)

    def forward(self, values, ids, noised, time, attend=None, outputs=None):
        b = time.shape[0]
        mask = self.visible.to(time.device)[None].expand(b, -1)
        attend = mask if attend is None else attend & mask
        return self.model(values, ids, noised, time, attend, outputs)


# ------------------------------------------------------------------------------ (a) and (b)
def generate(trained, args, decoder, device) -> dict:
    """Motion-conditioned candidates (a, b) and unconditional ones (b), decoded and scored."""
    from tt.baselines.evaluate import evaluate_designs
    from tt.dit.ddim import CosineDDIM
    from tt.dit.sampling import sample
    from tt.dit.tasks import ROBOT
    from tt.guidance.predicted import build_query
    from tt.guidance.zeroth import CandidateSampler, embodiment_batch
    from tt.sim.rewards import get_reward

    cfg = get_reward("tracking", SPACE)
    motions = validation_motions(args.motions)
    sampler = CandidateSampler(trained, device)
    # designs: candidates decoded to ViperX designs (warp rollout); mjcf: the detokenized
    # robots themselves (the oracle, which runs any fixed-base arm with an ee_0 site).
    cond = {
        "models": [],
        "designs": [],
        "distances": [],
        "failures": {},
        "sets": {
            "design": {"motion": [], "predicted": [], "simulated": []},
            "mjcf": {"motion": [], "predicted": [], "simulated": []},
        },
    }
    sample_s = decode_s = sim_s = 0.0
    for j, m in enumerate(motions):
        t = time.perf_counter()
        gen = sampler.run([m], cfg, args.samples, seed=args.seed + j, num_steps=args.num_steps)
        sample_s += time.perf_counter() - t
        t = time.perf_counter()
        dec = decoder(embodiment_batch(trained.layout, trained.normalizer, gen.tokens))
        decode_s += time.perf_counter() - t
        cond["models"] += [x for x, _, _ in dec]
        cond["designs"] += [d for _, d, _ in dec]
        cond["distances"] += [k for _, _, k in dec]
        t = time.perf_counter()
        ok = [i for i, (_, d, _) in enumerate(dec) if d is not None]
        if ok:
            ev = evaluate_designs([dec[i][1] for i in ok], [m], "tracking", backend=args.backend, device=args.device)
            sets = cond["sets"]["design"]
            sets["motion"] += [m.name] * len(ok)
            sets["predicted"] += [float(gen.reward[i, 0]) for i in ok]
            sets["simulated"] += [float(r) for r in ev.reward[:, 0]]
        loaded = [i for i, (x, _, _) in enumerate(dec) if x is not None]
        scored = oracle_rewards([dec[i][0] for i in loaded], m, cond["failures"])
        sets = cond["sets"]["mjcf"]
        for i, r in zip(loaded, scored):
            if r is not None:
                sets["motion"].append(m.name)
                sets["predicted"].append(float(gen.reward[i, 0]))
                sets["simulated"].append(r)
        sim_s += time.perf_counter() - t
        emit(
            part="a",
            motion=m.name,
            steps=m.steps,
            samples=args.samples,
            decoded=len(ok),
            loaded=len(loaded),
            simulated_mjcf=sum(r is not None for r in scored),
            predicted_mean=float(np.mean(gen.reward[:, 0])),
        )
    cond["seconds"] = {"sample": sample_s, "decode": decode_s, "simulate": sim_s}

    uncond = {"models": [], "designs": [], "distances": [], "seconds": {}}
    if args.unconditional:
        t = time.perf_counter()
        model = NoMotion(trained.model).to(device).eval()
        q = build_query(trained.layout, trained.normalizer, motions[0], args.unconditional, device=device)
        gen = torch.Generator(device=device).manual_seed(args.seed + 1000)
        res = sample(
            model, q.tokens, ROBOT, scheduler=CosineDDIM(ROBOT.diffusion_steps), num_steps=args.num_steps, generator=gen
        )
        uncond["seconds"]["sample"] = time.perf_counter() - t
        t = time.perf_counter()
        dec = decoder(embodiment_batch(trained.layout, trained.normalizer, res.tokens))
        uncond["seconds"]["decode"] = time.perf_counter() - t
        uncond["models"] = [x for x, _, _ in dec]
        uncond["designs"] = [d for _, d, _ in dec]
        uncond["distances"] = [k for _, _, k in dec]
    return {"motions": [m.name for m in motions], "cond": cond, "uncond": uncond}


def scatter_plot(sets: dict, titles: dict, path: Path) -> None:
    """One panel per scored set: predicted vs simulated reward, coloured by motion."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [k for k in sets if sets[k]["predicted"]]
    fig, axes = plt.subplots(1, len(names), figsize=(4.6 * len(names), 4.4), dpi=120, squeeze=False)
    for ax, key in zip(axes[0], names):
        c = sets[key]
        p, s = np.asarray(c["predicted"]), np.asarray(c["simulated"])
        for name in sorted(set(c["motion"]), key=c["motion"].index):
            sel = np.array([m == name for m in c["motion"]])
            ax.scatter(p[sel], s[sel], s=14, alpha=0.75, label=name)
        hi = max(float(p.max(initial=1)), float(s.max(initial=1))) * 1.05
        lo = min(0.0, float(p.min(initial=0)), float(s.min(initial=0)))
        ax.plot([lo, hi], [lo, hi], color="0.6", lw=1, ls="--")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_xlabel("predicted tracking reward (model's dynamics tokens)")
        ax.set_ylabel("simulated tracking reward (DiffIK)")
        ax.set_title(titles[key], fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def section_a(out: dict, args) -> str:
    sets = out["cond"]["sets"]
    labels = {"design": f"nearest ViperX designs, `{args.backend}` rollout", "mjcf": "detokenized MJCF robots, oracle"}
    stats, rows, titles = {}, [], {}
    for key, c in sets.items():
        p, s = np.asarray(c["predicted"]), np.asarray(c["simulated"])
        stats[key] = (pearson(p, s), spearman(p, s), len(p))
        titles[key] = f"{labels[key]}: Pearson r = {stats[key][0]:.2f} (n = {len(p)})"
        emit(part="a", robots=key, pearson=stats[key][0], spearman=stats[key][1], points=int(len(p)))
        for name in out["motions"]:
            sel = np.array([m == name for m in c["motion"]], dtype=bool)
            if sel.any():
                rows.append(
                    f"| {labels[key]} | {name} | {int(sel.sum())} | {p[sel].mean():.1f} | {s[sel].mean():.1f} | "
                    f"{pearson(p[sel], s[sel]):.2f} |"
                )
    png = Path(args.out).with_name(Path(args.out).stem + "_reward.png")
    if any(st[2] for st in stats.values()):
        scatter_plot(sets, titles, png)
    secs = out["cond"]["seconds"]
    total = len(out["cond"]["designs"])
    return "\n".join(
        [
            "## (a) Predicted vs simulated tracking reward",
            "",
            f'What is compared (the paper\'s "Predicted Reward Accuracy" figure): for {len(out["motions"])} validation '
            f"motions (held out from training), the model generates {args.samples} robots per motion ({total} in all; "
            f"motion-to-robot, {args.num_steps} DDIM steps, eta 0) and predicts each one's tracking reward "
            "from its own "
            "predicted track-link tokens (8 evenly placed steps, scaled by T / 8: `tt.guidance.predicted`, what "
            "Zeroth-Order ranks by). Each generated robot is then simulated on its motion with the DiffIK "
            "controller and "
            "scored by `tt.sim.rewards`, two ways: decoded to the nearest ViperX design (what `tt optimize` returns: "
            "a candidate whose token structure matches no discrete choice exactly is projected onto the nearest one, "
            "`tt.tokens.design_from_tokens(max_distance=None)`), and as the detokenizer's MJCF "
            "robot itself (run by the MuJoCo + mink oracle; robots it cannot drive are left out).",
            "",
            *[
                f"- {labels[k]}: **Pearson r = {st[0]:.2f}** (Spearman {st[1]:.2f}) over {st[2]} of {total} robots"
                for k, st in stats.items()
            ],
            "",
            f"The target for the shipped model is r >= 0.7. Scatter: `{png.name}`."
            + (
                ""
                if not out["cond"]["failures"]
                else " Detokenized robots the oracle could not run: "
                + "; ".join(f"{n} x {why}" for why, n in sorted(out["cond"]["failures"].items(), key=lambda x: -x[1]))
                + "."
            ),
            "",
            "| robots | motion | scored | predicted mean | simulated mean | Pearson r |",
            "|---|---|---:|---:|---:|---:|",
            *rows,
            "",
            f"Time: sampling {secs['sample']:.0f} s, decoding {secs['decode']:.0f} s, simulation "
            f"{secs['simulate']:.0f} s.",
            "",
            f"![predicted vs simulated]({png.name})",
            "",
        ]
    )


def section_d(trained, args, space) -> str:
    """Held-out designs given to the model (inpainting); predicted vs simulated tracking reward."""
    from tt.baselines.evaluate import evaluate_designs
    from tt.dit.ddim import CosineDDIM
    from tt.dit.sampling import sample
    from tt.dit.tasks import ROBOT
    from tt.guidance.predicted import PredictedReward, design_query
    from tt.sim.rewards import RewardInputs, evaluate, get_reward

    cfg = get_reward("tracking", SPACE)
    designs = space.sample(args.heldout_designs, seed=args.design_seed + 1)
    models = [space.model(d) for d in designs]
    sets = {
        "model": {"motion": [], "predicted": [], "simulated": []},
        "estimator": {"motion": [], "predicted": [], "simulated": []},
    }
    sample_s = sim_s = 0.0
    gen = torch.Generator(device=args.device)
    for j, m in enumerate(validation_motions(args.motions)):
        t = time.perf_counter()
        query, known = design_query(trained.layout, trained.normalizer, m, models, device=args.device)
        res = sample(
            trained.model,
            query.tokens,
            ROBOT,
            scheduler=CosineDDIM(ROBOT.diffusion_steps),
            num_steps=args.num_steps,
            known=known,
            generator=gen.manual_seed(args.seed + 500 + j),
        )
        with torch.no_grad():
            predicted = PredictedReward(trained.layout, trained.normalizer, cfg, query)(res.tokens.values).cpu().numpy()
        sample_s += time.perf_counter() - t
        t = time.perf_counter()
        ev = evaluate_designs(designs, [m], "tracking", backend=args.backend, device=args.device)
        ep = ev.episode
        st = query.steps[0].to(ep.ee_pos.device)
        inputs = RewardInputs(
            ep.ee_pos[:, st].double(),
            ep.ee_quat[:, st].double(),
            ep.target_pos[:, st].double(),
            ep.target_quat[:, st].double(),
        )
        estimate = (m.steps / trained.layout.steps) * evaluate(inputs, cfg).reward.cpu().numpy()
        sim_s += time.perf_counter() - t
        for key, pred in (("model", predicted), ("estimator", estimate)):
            sets[key]["motion"] += [m.name] * len(designs)
            sets[key]["predicted"] += [float(x) for x in pred]
            sets[key]["simulated"] += [float(x) for x in ev.reward[:, 0]]
        emit(
            part="d",
            motion=m.name,
            pearson=pearson(predicted, ev.reward[:, 0]),
            estimator=pearson(estimate, ev.reward[:, 0]),
        )
    labels = {
        "model": "the model's predicted dynamics (inpainted)",
        "estimator": "the same estimator on the simulated poses (its ceiling)",
    }
    rows, titles, lines = [], {}, []
    for key, c in sets.items():
        p, s_ = np.asarray(c["predicted"]), np.asarray(c["simulated"])
        r, rho = pearson(p, s_), spearman(p, s_)
        titles[key] = f"{labels[key]}: r = {r:.2f}"
        lines.append(f"- {labels[key]}: **Pearson r = {r:.2f}** (Spearman {rho:.2f}) over {len(p)} episodes")
        emit(part="d", reward_from=key, pearson=r, spearman=rho, points=int(len(p)))
        for name in dict.fromkeys(c["motion"]):
            sel = np.array([x == name for x in c["motion"]])
            rows.append(
                f"| {labels[key]} | {name} | {int(sel.sum())} | {p[sel].mean():.1f} | {s_[sel].mean():.1f} | "
                f"{pearson(p[sel], s_[sel]):.2f} |"
            )
    png = Path(args.out).with_name(Path(args.out).stem + "_heldout.png")
    scatter_plot(sets, titles, png)
    return "\n".join(
        [
            "## (d) Predicted vs simulated tracking reward on held-out episodes",
            "",
            f"{len(designs)} held-out ViperX designs (`space.sample({len(designs)}, "
            f"seed={args.design_seed + 1})`) x the "
            f"{args.motions} validation motions of (a), simulated with DiffIK (`{args.backend}`). The model "
            "is given each "
            "design: its embodiment tokens fill the motion-to-robot query and are inpainted (noised to each "
            "DDIM step's "
            f"level, `tt.guidance.predicted.design_query`), the model predicts the dynamics ({args.num_steps} "
            "DDIM steps, "
            "eta 0), and the reward is computed from its predicted track-link tokens at 8 evenly placed "
            "steps, scaled by T / 8.",
            "",
            *lines,
            "",
            "The target for the shipped model is r >= 0.7. The estimator's ceiling shows that 8 steps suffice to rank "
            f"episodes; what is missing is the model's knowledge of how a design moves. Scatter: `{png.name}`.",
            "",
            "| reward from | motion | episodes | predicted mean | simulated mean | Pearson r |",
            "|---|---|---:|---:|---:|---:|",
            *rows,
            "",
            f"Time: sampling {sample_s:.0f} s, simulation and scoring {sim_s:.0f} s.",
            "",
            f"![held-out predicted vs simulated]({png.name})",
            "",
        ]
    )


def training_choices(data: str, space) -> tuple[dict[str, dict[str, float]], int] | None:
    """Share of the training episodes per option of each discrete choice of interest."""
    from tt.tokens.store import TokenStore

    if not data or not Path(data).exists():
        return None
    store = TokenStore(data, verify="none")
    counts: dict[str, dict[str, int]] = {}
    total = 0
    for r in store.readers:
        designs = r.designs(space)
        per_design = np.bincount(r.field("design").astype(np.int64), minlength=len(designs))
        for d, n in zip(designs, per_design):
            for k, v in choices(space, d).items():
                counts.setdefault(k, {}).setdefault(v, 0)
                counts[k][v] += int(n)
        total += int(per_design.sum())
    return {k: {o: n / total for o, n in v.items()} for k, v in counts.items()}, total


def mjcf_choices(model) -> dict[str, str]:
    """DoF count and mount of a robot read from its compiled model (for robots that are not a
    ViperX design): DoF = hinge and slide joints ("other" outside 5..7); mount from the world
    direction of the first joint's axis (the waist turns about the mount's normal): up ->
    upright, down -> downward, horizontal -> left (axis -y side) or right (+y side)."""
    import mujoco

    dof = str(model.njnt) if str(model.njnt) in ("5", "6", "7") else "other"
    if model.njnt == 0:
        return {"dof": dof, "mount": "none"}
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    ax = data.xaxis[0]
    mount = "upright" if ax[2] > 0.5 else "downward" if ax[2] < -0.5 else "left" if ax[1] < 0 else "right"
    return {"dof": dof, "mount": mount}


def mjcf_classifier_accuracy(space, n: int = 200, seed: int = 7) -> float:
    """Share of `n` random ViperX designs whose `mjcf_choices` equal their true choices."""
    ok = 0
    for d in space.sample(n, seed):
        c = choices(space, d)
        got = mjcf_choices(space.model(d))
        ok += got["dof"] == c["dof"] and got["mount"] == c["mount"]
    return ok / n


def section_b(out: dict, args, space) -> str:
    train = training_choices(args.data, space)
    sets = {"motion-conditioned": out["cond"], "unconditional": out["uncond"]}
    sets = {k: v for k, v in sets.items() if v["models"]}
    lines = [
        "## (b) Samples decode to robots; their choices",
        "",
        "Motion-conditioned: the candidates of (a). Unconditional: the same query with the target-pose "
        "tokens masked out of attention, so the model sees no motion. The model was not trained with "
        'conditioning dropout, so this input is outside its training distribution. "Loads": the generic '
        "detokenizer's MJCF compiles in MuJoCo. \"ViperX structure\": the tokens' structure is exactly "
        'that of a discrete choice of the space (token counts and every binary attribute). "Nearest ViperX '
        'design": projected onto the nearest structure and fitted, the design compiles (what the optimizers '
        "return); distance: binary token attributes changed by the projection (a missing or extra token counts "
        "as its attributes + 1).",
        "",
        "| samples | count | loads in MuJoCo | ViperX structure | nearest ViperX design | distance (median, "
        "90th pct) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, s in sets.items():
        n = len(s["models"])
        loads = 100.0 * np.mean([x is not None for x in s["models"]])
        exact = 100.0 * np.mean([k == 0 and d is not None for d, k in zip(s["designs"], s["distances"])])
        dec = 100.0 * np.mean([d is not None for d in s["designs"]])
        dist = np.array([k for d, k in zip(s["designs"], s["distances"]) if d is not None], dtype=float)
        med = f"{np.median(dist):.0f}, {np.percentile(dist, 90):.0f}" if len(dist) else "–"
        lines.append(f"| {name} | {n} | {loads:.1f} % | {exact:.1f} % | {dec:.1f} % | {med} |")
        emit(
            part="b",
            samples=name,
            count=n,
            loads_pct=loads,
            exact_pct=exact,
            decoded_pct=dec,
            distances=[int(k) for k in s["distances"]],
        )
    # Choices two ways: of the decoded ViperX designs, and read off the loadable MJCF robots.
    columns = {}
    for name, s in sets.items():
        columns[f"{name}, designs"] = [choices(space, d) for d in s["designs"] if d is not None]
        columns[f"{name}, MJCF"] = [mjcf_choices(x) for x in s["models"] if x is not None]
    accuracy = mjcf_classifier_accuracy(space)
    lines += [
        "",
        'Distribution of the samples\' choices: share of the nearest ViperX designs ("designs") and of the '
        'loadable MJCF robots ("MJCF": DoF = joint count, mount from the first joint\'s world axis; on '
        f"200 random ViperX designs this reading gives the true DoF and mount for {100 * accuracy:.0f} %); "
        "training: share of the training episodes.",
        "",
        "| choice | option | training |" + "".join(f" {k} (n={len(v)}) |" for k, v in columns.items()),
        "|---|---|---:|" + "---:|" * len(columns),
    ]
    tv = {}
    for key in ("dof", "mount"):
        options = list(next(p.options for p in space.discrete_params(space.nominal().discrete) if p.name == key))
        extra = sorted({c[key] for v in columns.values() for c in v} - set(options))
        shares = {
            k: {o: (sum(c[key] == o for c in v) / len(v)) if v else float("nan") for o in options + extra}
            for k, v in columns.items()
        }
        for o in options + extra:
            tr = train[0][key].get(o, 0.0) if train else float("nan")
            cells = "".join(" – |" if np.isnan(shares[k][o]) else f" {100 * shares[k][o]:.1f} % |" for k in columns)
            lines.append(f"| {key} | {o} | {100 * tr:.1f} % |" + cells)
        if train:
            for k in columns:
                tv[(key, k)] = 0.5 * sum(abs(shares[k][o] - train[0][key].get(o, 0.0)) for o in options + extra)
    lines.append("")
    if train:
        lines.append(
            f"Training data: {train[1]} episodes of `{args.data}`. Total variation distance to it: "
            + "; ".join(f"{k} ({n}) {v:.2f}" for (k, n), v in tv.items())
            + "."
        )
        emit(part="b", total_variation={f"{k}/{n}": v for (k, n), v in tv.items()})
    else:
        lines.append(f"Training data `{args.data}` not found: no training column.")
    secs = out["uncond"]["seconds"]
    if secs:
        lines.append(f"Unconditional: sampling {secs['sample']:.0f} s, decoding {secs['decode']:.0f} s.")
    lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------------------ (c)
def teacher_forced(trained, task, args, space: str = SPACE, config=None) -> dict:
    """One-step control accuracy on fresh episodes: the control task's query built from
    recorded windows (true current state and targets), its predicted commands against the
    recorded ones, and the same error for holding the current joint positions (ViperX: one
    position actuator per hinge, in joint order) and for repeating the last command (the
    window's first, which led to the current state). config: the closed loop's
    `tt.dit.policies.ControllerConfig` (None: its defaults), whose DDIM steps and spacing
    each query is sampled with.

    Returns {"windows", "episodes", "slots": [(slot, model, hold, spread, repeat), ...]} (RMSE in rad)."""
    from tt.dit.ddim import CosineDDIM
    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.dit.policies import ControllerConfig
    from tt.dit.sampling import sample
    from tt.dit.tasks import task_windows

    config = ControllerConfig() if config is None else config
    # Unperturbed, as the shipped checkpoint's dataset was generated.
    source = OnlineTokenSource(OnlineConfig(space=space, seed=args.design_seed, action_noise=0.0), device=args.device)
    layout, norm, S = trained.layout, trained.normalizer, trained.layout.steps
    raw = task_windows(source, layout, args.teacher_windows, task, torch.Generator().manual_seed(args.seed))
    res = sample(
        trained.model,
        norm.normalize(raw).to(args.device),
        task,
        scheduler=CosineDDIM(task.diffusion_steps),
        num_steps=config.num_steps,
        spacing=config.spacing,
        generator=torch.Generator(device=args.device).manual_seed(args.seed),
    )
    n, P = raw.values["control"].shape[0], layout["control"].per_step
    pred = norm.denormalize_values("control", res.tokens.values["control"].cpu()).reshape(n, S, P)
    true = raw.values["control"].reshape(n, S, P)
    real = raw.mask["control"].reshape(n, S, P)
    qpos = raw.values["dyna_joint_obs"].reshape(n, S, -1, 2)[:, 0, :P, 0]  # (n, P): current joint positions
    rmse = lambda e: float(e.pow(2).mean().sqrt())  # noqa: E731
    out = {"windows": n, "episodes": len(source), "slots": []}
    for k in range(S):
        m = real[:, k]
        out["slots"].append(
            (
                k,
                rmse((pred[:, k] - true[:, k])[m]),
                rmse((qpos - true[:, k])[m]),
                float(true[:, k][m].std()),
                rmse((true[:, 0] - true[:, k])[m & real[:, 0]]),
            )
        )
    emit(part="c", teacher_forced=out)
    return out


def section_c(trained, task, args, space) -> str:
    from tt.baselines.evaluate import score_episode
    from tt.dit.closed_loop import closed_loop_rollout
    from tt.dit.policies import ControllerConfig, HoldPolicy, IKPolicy, model_rollout
    from tt.sim.validate import oracle_rollout

    designs = space.sample(args.designs, seed=args.design_seed)
    motions = cut(validation_motions(args.control_motions), args.control_steps)
    t = time.perf_counter()
    ep_model = model_rollout(
        designs,
        motions,
        trained,
        task=task,
        config=ControllerConfig(seed=args.seed),
        device=args.device,
        progress=args.progress,
    )
    model_s = time.perf_counter() - t
    t = time.perf_counter()
    ep_oracle = oracle_rollout(designs, motions)
    oracle_s = time.perf_counter() - t
    r_model, m_model = score_episode(ep_model, designs, motions, "tracking")
    r_oracle, m_oracle = score_episode(ep_oracle, designs, motions, "tracking")
    # The floor and the teacher in the same closed loop: a still arm, and DiffIK itself.
    r_still, m_still = score_episode(closed_loop_rollout(designs, motions, HoldPolicy()), designs, motions, "tracking")
    r_ik, m_ik = score_episode(closed_loop_rollout(designs, motions, IKPolicy()), designs, motions, "tracking")
    share = float(r_model.mean() / r_oracle.mean())
    still_share, ik_share = float(r_still.mean() / r_oracle.mean()), float(r_ik.mean() / r_oracle.mean())
    r = pearson(r_oracle.ravel(), r_model.ravel())
    tf = teacher_forced(trained, task, args)
    emit(
        part="c",
        designs=len(designs),
        motions=len(motions),
        steps=[m.steps for m in motions],
        model_reward=float(r_model.mean()),
        oracle_reward=float(r_oracle.mean()),
        share=share,
        pearson=r,
        still_share=still_share,
        ik_share=ik_share,
        model_seconds=model_s,
        oracle_seconds=oracle_s,
    )

    def row(name, m):
        return (
            f"| {name} | {np.nanmean(m['pos_err']):.1f} | {np.nanmean(m['orn_err']):.1f} | "
            f"{100 * np.mean(m['survival']):.1f} | {np.mean(m['reward']):.1f} | "
            f"{100 * np.mean(m['reward']) / r_oracle.mean():.1f} % |"
        )

    steps = sorted({m.steps for m in motions})
    length = f"cut to their first {args.control_steps} control steps" if args.control_steps else "whole"
    return "\n".join(
        [
            "## (c) The model as controller",
            "",
            f"{len(designs)} held-out ViperX designs (`space.sample({args.designs}, seed={args.design_seed})`; the "
            f"training shards draw from other seeds) x {len(motions)} validation motions "
            f"({', '.join(m.name for m in motions)}; "
            f"{length}: {steps[0]}..{steps[-1]} steps). Model: `tt.dit.policies.ModelPolicy`, "
            f"{ControllerConfig().num_steps} DDIM step(s) per control step ({ControllerConfig().spacing} "
            "spacing), each command "
            "the mean of the recent queries' predictions for it (`ControllerConfig`'s defaults), batched "
            "over the running "
            "worlds, Warp physics. "
            "Oracle: MuJoCo C + mink DiffIK (`tt.sim.validate`). Both start at the oracle's start posture.",
            "",
            f"**Model / oracle mean tracking reward: {100 * share:.1f} %** (the paper's small model: 83 %, on the "
            "bimanual space). Pearson r of per-episode rewards, model vs oracle: "
            f"{r:.2f} over {r_model.size} episodes. A still arm (every step repeats the start posture's command, "
            f"`tt.dit.policies.HoldPolicy`) scores {100 * still_share:.1f} % in the same closed loop, DiffIK "
            "(the teacher, "
            f"`IKPolicy`) {100 * ik_share:.1f} %.",
            "",
            "| controller | pos err (cm) | orn err (deg) | survival (%) | tracking reward | share of the oracle's |",
            "|---|---:|---:|---:|---:|---:|",
            row("DiT (this checkpoint)", m_model),
            row("a still arm (the start posture's command repeated)", m_still),
            row("DiffIK in the same closed loop (the teacher)", m_ik),
            row("MuJoCo + mink (oracle)", m_oracle),
            "",
            f"Time: model controller {model_s:.0f} s ({ep_model.worlds} worlds x {ep_model.steps} steps), "
            f"oracle {oracle_s:.0f} s.",
            "",
            f"One step at a time (teacher-forced): {tf['windows']} windows of 8 consecutive steps from "
            f"{tf['episodes']} fresh "
            f"episodes (`tt.dit.online` refresh 0 with seed {args.design_seed}: designs and augmented motions "
            "no training "
            "shard drew; no control perturbation), the control query built from the recorded current state "
            "and targets, "
            f"{ControllerConfig().num_steps} DDIM step(s) ({ControllerConfig().spacing} spacing); RMSE of the "
            "predicted joint-position commands against the recorded DiffIK commands, beside the RMSE of simply holding "
            "the current joint positions. Where the model's error is not below holding's, the control head has not "
            "learned DiffIK's increments. "
            + (
                "Commands are predicted as residuals from the current joint positions "
                "(delta actions, `--anchor-control`)."
                if "control" in trained.model.anchors
                else "Commands are absolute joint targets, normalised over their whole range."
            ),
            "",
            "| window step | model RMSE (rad) | hold current position RMSE (rad) | spread of the commands (rad) |",
            "|---:|---:|---:|---:|",
            *[f"| {k} | {a:.3f} | {b:.3f} | {c:.2f} |" for k, a, b, c, _ in tf["slots"]],
            "",
        ]
    )


# ------------------------------------------------------------------------------ file
def write_sections(path: Path, header: str, sections: dict[str, str]) -> None:
    """Replace the header and the given parts' sections of the results file, keep the others."""
    old = path.read_text() if path.exists() else ""
    kept = {m.group(1): m.group(2) for m in re.finditer(r"<!-- part (\w) -->\n(.*?)<!-- /part \1 -->\n", old, re.S)}
    kept.update(sections)
    body = "".join(f"<!-- part {k} -->\n{kept[k]}<!-- /part {k} -->\n" for k in sorted(kept))
    path.write_text(header + "\n" + body)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="checkpoint file or run folder (its latest checkpoint)")
    parser.add_argument(
        "--parts", default="abcd", help="which parts to run: any of a, b, c, d (a and b share their samples)"
    )
    parser.add_argument("--motions", type=int, default=4, help="(a, b) validation motions")
    parser.add_argument("--samples", type=int, default=16, help="(a, b) candidates per motion")
    parser.add_argument("--num-steps", type=int, default=100, help="(a, b) DDIM steps of the motion-to-robot process")
    parser.add_argument("--unconditional", type=int, default=64, help="(b) unconditional samples (0: none)")
    parser.add_argument(
        "--fit-top-k",
        type=int,
        default=2,
        help="(a, b) discrete choices whose continuous choices are fitted per candidate",
    )
    parser.add_argument("--backend", default="warp", help="(a) rollout backend of the simulated reward: warp | mujoco")
    parser.add_argument(
        "--data", default=None, help="(b) training dataset (default: the checkpoint's train_config data)"
    )
    parser.add_argument("--designs", type=int, default=25, help="(c) held-out designs")
    parser.add_argument("--heldout-designs", type=int, default=32, help="(d) held-out designs per motion")
    parser.add_argument("--design-seed", type=int, default=20261122, help="(c) seed of the held-out designs")
    parser.add_argument("--control-motions", type=int, default=5, help="(c) validation motions")
    parser.add_argument(
        "--control-steps", type=int, default=100, help="(c) control steps per motion (0: whole motions)"
    )
    parser.add_argument(
        "--teacher-windows", type=int, default=256, help="(c) windows of the one-step (teacher-forced) check"
    )
    parser.add_argument("--seed", type=int, default=0, help="sampling seed")
    parser.add_argument("--device", default="cpu", help="torch / Warp device")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--progress", action="store_true", help="(c) progress bar over control steps")
    parser.add_argument("--out", default=str(RESULTS / "dit_eval.md"), help="results markdown file")
    args = parser.parse_args()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)  # the sections write their plots beside it
    if set(args.parts) - set("abcd"):
        parser.error(f"--parts {args.parts!r}: use letters a, b, c, d")
    if args.threads:
        torch.set_num_threads(args.threads)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from tt.dit.checkpoint import latest_checkpoint, load_checkpoint, load_model
    from tt.dit.policies import control_task
    from tt.sim.designs import get_space

    ckpt = Path(args.checkpoint)
    if ckpt.is_dir():
        found = latest_checkpoint(ckpt)
        if found is None:
            parser.error(f"run folder {ckpt} has no checkpoints")
        ckpt = found
    state = load_checkpoint(ckpt)
    train_cfg = state.get("train_config") or {}
    if args.data is None:
        args.data = train_cfg.get("data", "")
    trained = load_model(ckpt, device=args.device)
    task = control_task(ckpt)
    del state
    space = get_space(SPACE)
    load_before = os.getloadavg()
    started = time.perf_counter()
    sections = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tokenizer approximations of decoded candidates
        if "a" in args.parts or "b" in args.parts:
            decoder = Decoder(space, args.fit_top_k)
            out = generate(trained, args, decoder, args.device)
            if "a" in args.parts:
                sections["a"] = section_a(out, args)
            if "b" in args.parts:
                sections["b"] = section_b(out, args, space)
        if "c" in args.parts:
            sections["c"] = section_c(trained, task, args, space)
        if "d" in args.parts:
            sections["d"] = section_d(trained, args, space)
    load_after = os.getloadavg()
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    sections = {k: f"_Run {stamp}, checkpoint step {trained.step}._\n\n{v}" for k, v in sections.items()}
    header = "\n".join(
        [
            "# DiT evaluation (ViperX)",
            "",
            machine_header(args.device).rstrip(),
            f"- torch threads {torch.get_num_threads()}; load average (1 min) before / after the latest run: "
            f"{load_before[0]:.1f} / {load_after[0]:.1f}; latest run: parts {args.parts}, "
            f"{time.perf_counter() - started:.0f} s "
            "(each section names the run and checkpoint it comes from)",
            f"- latest checkpoint: `{ckpt}` (step {trained.step}; {trained.model.parameter_count() / 1e6:.2f} "
            "M parameters, "
            f"size {train_cfg.get('size', '?')}, task {train_cfg.get('task', '?')}, batch "
            f"{train_cfg.get('batch_size', '?')}, "
            f"data `{train_cfg.get('data', '?')}`)",
            f"- command: `python benchmarks/dit_eval.py {' '.join(sys.argv[1:])}`",
            "",
        ]
    )
    out_path = Path(args.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    write_sections(out_path, header, sections)
    emit(part="written", path=str(out_path), seconds=time.perf_counter() - started)


if __name__ == "__main__":
    main()
