"""The paper's figures from a sweep (PNG, matplotlib), drawn from the same aggregation as the tables.

    python experiments/figures.py runs/sweeps/cpu [--out DIR]

exp1.png  return (and success for Reach/Push) vs test-time steps per family: CLAW, DR, ST, Oracle
exp2.png  return (and success) vs offline gradient steps (symlog x); CLAW's pass as a horizontal band
exp3.png  Cheetah/Walker return vs base parameter count (log x) for CLAW, FiLM, Concat; ratio to CLAW
exp4.png  return vs LoRA rank, and vs adapter size as % of the world model, FiLM/Concat for reference
exp5.png  Cheetah return: CLAW (joint) vs post-hoc hypernet
go1.png   Go1 return per running direction (forward, backward) per method, Exp 1 online and Exp 2 unadapted: the bimodality claim
controls.png  CLAW's (and CLAW + decoder's) return with its own minus with another environment's context, and return vs context size
training.png  training-episode return vs agent steps: ST per embodiment (experiment budget), and every method of
              Exp 1/2 per family, beside the random policy's return
A figure whose runs are missing is skipped with a message. Bands and error bars are 95% t-CIs.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402

from experiments.aggregate import (  # noqa: E402
    check_roots,
    controls_rows,
    load_sweep,
    random_policy_return,
    summarize,
    training_curves,
)
from experiments.sweep import SIZE_RANKS  # noqa: E402

COLORS = {
    "claw": "tab:red",
    "dr": "tab:blue",
    "st": "tab:green",
    "oracle": "black",
    "film": "tab:purple",
    "concat": "tab:orange",
    "posthoc": "tab:gray",
    "claw_decoder": "tab:pink",
}
LABELS = {
    "claw": "CLAW",
    "dr": "DR",
    "st": "ST",
    "oracle": "Oracle",
    "film": "FiLM",
    "concat": "Concat",
    "posthoc": "Post-hoc",
    "claw_decoder": "CLAW + reward decoder (not the paper's)",
}
METAWORLD = ("reach", "push")


def _ci(value):
    """A CI half-width, NaN where there is none (one seed): matplotlib draws no error bar for NaN, where 0 would
    draw a cap that reads as a very tight interval."""
    return math.nan if value is None else value


def _interval(metric, rows, ci_key="ci95"):
    """(lowers, uppers) of each row's mean +- CI, cut to what the metric can take (success in [0, 1], returns >= 0:
    every family's rewards are non-negative): at n = 2 (t = 12.7) a raw interval spans impossible values. NaN
    where a row has no CI."""
    top = 1.0 if metric.endswith("success") else math.inf
    half = [_ci(r[ci_key]) for r in rows]
    return (
        [math.nan if math.isnan(h) else max(0.0, r["mean"] - h) for r, h in zip(rows, half)],
        [math.nan if math.isnan(h) else min(top, r["mean"] + h) for r, h in zip(rows, half)],
    )


def _yerr(metric, rows, ci_key="ci95"):
    """_interval as matplotlib's asymmetric yerr."""
    lower, upper = _interval(metric, rows, ci_key)
    return [[r["mean"] - lo for r, lo in zip(rows, lower)], [hi - r["mean"] for r, hi in zip(rows, upper)]]


def _seeds(rows) -> str:
    """How many seeds the points of a figure average, for its title: "n = 3" or "n = 1-3"."""
    counts = sorted({int(r["n"]) for r in rows})
    return f"n = {counts[0]}" if len(counts) == 1 else f"n = {counts[0]}-{counts[-1]}"


def world_model_sizes(size: str, rank: int, obs_dim: int = 24, act_dim: int = 6) -> tuple[int, int, int]:
    """(base params, world-model params without policy, world-model LoRA params at rank)."""
    import claw_tdmpc2 as claw

    model = claw.WorldModel(obs_dim, act_dim, size, claw.Args())
    base = sum(p.numel() for p in model.base_parameters())
    _, n_wm, _ = claw.lora_layout(model, rank)
    return base, base - sum(p.numel() for p in model.policy.parameters()), n_wm


def select(rows, **match):
    return [r for r in rows if all(r[k] == v for k, v in match.items())]


def panels(families, prefix):
    """(family, metric, y label) per subplot: return for every family, plus success for Meta-World
    (the paper reports success there; at small budgets return is the less sparse signal)."""
    grid = [[(f, f"{prefix}_return", "episode return") for f in families]]
    if any(f in METAWORLD for f in families):
        grid.append([(f, f"{prefix}_success", "success") if f in METAWORLD else None for f in families])
    return grid


def save_panel_grid(families, prefix, draw, path):
    """One subplot per `panels` entry; draw(ax, family, metric) fills it; one legend, below the grid."""
    grid = panels(families, prefix)
    # constrained layout reserves room for an "outside" figure legend, so long labels no longer squeeze the panels
    fig, axes = plt.subplots(
        len(grid), len(families), figsize=(4.5 * len(families), 3.5 * len(grid) + 0.8), squeeze=False, layout="constrained"
    )
    for ax_row, panel_row in zip(axes, grid):
        for ax, panel in zip(ax_row, panel_row):
            if panel is None:
                ax.axis("off")
                continue
            family, metric, label = panel
            draw(ax, family, metric)
            ax.set(title=family, ylabel=label)
    handles = {}  # every method drawn in any panel (a family may lack some), once each
    for ax in axes.flat:
        for handle, name in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(name, handle)
    # outside: bands fill the panels
    fig.legend(handles.values(), handles.keys(), loc="outside lower center", ncols=len(families), fontsize="small")
    fig.savefig(path, dpi=120, bbox_inches="tight")  # "tight" keeps a legend wider than the panels whole


def figure_exp1(rows, curves, out) -> str | None:
    families = sorted({c["family"] for c in curves if c["method"] in ("dr", "st", "oracle")})
    if not families:
        return "exp1: no DR/ST/Oracle runs"

    def draw(ax, family, metric):
        for method in ("claw", "dr", "st", "oracle", "claw_decoder"):
            points = select(curves, family=family, method=method, metric=metric)
            if points:
                x, y = [p["step"] for p in points], [p["mean"] for p in points]
                # markers where a short evaluation leaves few points: a single one draws no line
                ax.plot(x, y, color=COLORS[method], label=LABELS[method], marker="o" if len(points) < 5 else None)
                ax.fill_between(x, *_interval(metric, points), color=COLORS[method], alpha=0.15)
        ax.set_xlabel("test-time environment steps")

    save_panel_grid(families, "online", draw, os.path.join(out, "exp1.png"))
    return None


def figure_exp2(rows, curves, out) -> str | None:
    families = sorted({r["family"] for r in rows if r["metric"] == "offline_return" and r["method"] in ("dr", "st", "oracle")})
    if not families:
        return "exp2: no DR/ST/Oracle offline sweeps"

    def draw(ax, family, metric):
        steps = [0]
        for method in ("dr", "st", "oracle"):
            points = select(rows, family=family, method=method, metric=metric)
            if points:
                steps += [p["x"] for p in points]
                ax.errorbar(
                    [p["x"] for p in points],
                    [p["mean"] for p in points],
                    yerr=_yerr(metric, points),
                    color=COLORS[method],
                    label=LABELS[method],
                    marker="o",
                    capsize=3,
                )
        for method in ("claw", "claw_decoder"):  # one hypernet pass each: a band
            for p in select(rows, family=family, method=method, metric=metric):
                ax.axhline(p["mean"], color=COLORS[method], label=f"{LABELS[method]}, 1 hypernet pass")
                (lower,), (upper,) = _interval(metric, [p])
                if not math.isnan(lower):
                    ax.axhspan(lower, upper, color=COLORS[method], alpha=0.15)
        ax.set_xscale("symlog", linthresh=1)
        ax.set_xlim(0, max(steps) * 1.5 + 1)
        ax.set_xlabel("offline gradient steps")

    save_panel_grid(families, "offline", draw, os.path.join(out, "exp2.png"))
    return None


def figure_exp3(rows, curves, out) -> str | None:
    cw = [
        r for r in select(rows, family="cheetah_walker", metric="online_return") if r["method"] in ("claw", "film", "concat")
    ]
    cw = [r for r in cw if r["method"] != "claw" or r["rank"] == SIZE_RANKS[r["size"]]]  # Exp 3 ties rank to size
    if len({r["size"] for r in cw}) < 2:
        return "exp3: fewer than two model sizes on cheetah_walker"
    fig, (ax, ax_ratio) = plt.subplots(1, 2, figsize=(9, 3.5))
    claw_by_size = {r["size"]: r["mean"] for r in cw if r["method"] == "claw"}
    for method in ("claw", "film", "concat"):
        points = sorted((world_model_sizes(r["size"], r["rank"])[0], r) for r in cw if r["method"] == method)
        if not points:
            continue
        ax.errorbar(
            [p for p, _ in points],
            [r["mean"] for _, r in points],
            yerr=_yerr("return", [r for _, r in points]),
            color=COLORS[method],
            label=LABELS[method],
            marker="o",
            capsize=3,
        )
        ratio = [(p, r["mean"] / claw_by_size[r["size"]]) for p, r in points if claw_by_size.get(r["size"])]
        if ratio:
            ax_ratio.plot(*zip(*ratio), color=COLORS[method], marker="o", label=LABELS[method])
    ax.set(xscale="log", xlabel="base parameters", ylabel="episode return", title="return vs model size")
    ax_ratio.set(xscale="log", xlabel="base parameters", ylabel="return / CLAW return", title="relative to CLAW")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out, "exp3.png"), dpi=120)
    return None


def figure_exp4(rows, curves, out) -> str | None:
    cw = select(rows, family="cheetah_walker", metric="online_return")
    claw = [r for r in cw if r["method"] == "claw"]
    size_counts = {}
    for r in claw:
        size_counts[r["size"]] = size_counts.get(r["size"], 0) + 1
    if not size_counts or max(size_counts.values()) < 2:
        return "exp4: fewer than two ranks at one size on cheetah_walker"
    size = max(size_counts, key=size_counts.get)
    claw = sorted((r for r in claw if r["size"] == size), key=lambda r: r["rank"])
    _, world_model, _ = world_model_sizes(size, 1)
    fig, (ax_rank, ax_pct) = plt.subplots(2, 1, figsize=(4.5, 6))
    ranks = [r["rank"] for r in claw]
    percents = [100 * world_model_sizes(size, r["rank"])[2] / world_model for r in claw]
    for ax, x in ((ax_rank, ranks), (ax_pct, percents)):
        ax.errorbar(
            x, [r["mean"] for r in claw], yerr=_yerr("return", claw), color=COLORS["claw"], marker="o", capsize=3, label="CLAW"
        )
    for method in ("film", "concat"):
        for r in select(cw, method=method, size=size):
            ax_rank.axhline(r["mean"], color=COLORS[method], linestyle="--", label=LABELS[method])
            (lower,), (upper,) = _interval("return", [r])
            if not math.isnan(lower):
                ax_rank.axhspan(lower, upper, color=COLORS[method], alpha=0.1)
            if method == "film":  # FiLM spends a scale and a shift per world-model hidden feature
                film_percent = 100 * film_parameters(size) / world_model
                ax_pct.errorbar(
                    [film_percent],
                    [r["mean"]],
                    yerr=_yerr("return", [r]),
                    color=COLORS[method],
                    marker="s",
                    capsize=3,
                    label="FiLM",
                )
    drawn = claw + [r for r in select(cw, size=size) if r["method"] in ("film", "concat")]  # not post-hoc: Exp 5's
    ax_rank.set(
        xscale="log", xlabel="LoRA rank", ylabel="episode return", title=f"Cheetah/Walker, size {size}, {_seeds(drawn)}"
    )
    ax_pct.set(xscale="log", xlabel="adapter size (% of world model)", ylabel="episode return")
    for ax in (ax_rank, ax_pct):  # plain numbers at the data points, not 4x10^0 minor ticks
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax_rank.set_xticks(ranks)
    ax_pct.set_xticks([round(p, 1) for p in percents])
    ax_rank.legend()
    ax_pct.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out, "exp4.png"), dpi=120)
    return None


def film_parameters(size: str) -> int:
    """World-model FiLM parameters: 2 x output features of every adapted (hidden) layer."""
    import claw_tdmpc2 as claw

    model = claw.WorldModel(24, 6, size, claw.Args())
    return sum(
        2 * getattr(model, name).weights[i].shape[:-1].numel()
        for name in model.WORLD_MODEL_MODULES
        for i in range(getattr(model, name).num_normed)
    )


def figure_exp5(rows, curves, out) -> str | None:
    posthoc = select(rows, method="posthoc", metric="online_return_env0")
    if not posthoc:
        return "exp5: no post-hoc runs"
    size, rank = posthoc[0]["size"], posthoc[0]["rank"]
    joint = select(rows, method="claw", family="cheetah_walker", size=size, rank=rank, metric="online_return_env0")
    bars = [("CLAW (joint)", joint[0], COLORS["claw"])] if joint else []
    bars.append(("Post-hoc", posthoc[0], COLORS["posthoc"]))
    fig, ax = plt.subplots(figsize=(3.5, 3.5))
    ax.bar(
        [b[0] for b in bars],
        [b[1]["mean"] for b in bars],
        yerr=_yerr("return", [b[1] for b in bars]),
        color=[b[2] for b in bars],
        capsize=4,
    )
    ax.set(ylabel="Cheetah episode return", title=f"size {size}, rank {rank}, {_seeds([b[1] for b in bars])}")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "exp5.png"), dpi=120)
    return None


def figure_go1(rows, curves, out) -> str | None:
    """Go1's return per direction and method, side by side, online (Exp 1) and unadapted (Exp 2 at 0 steps; CLAW's
    one pass): DR's one model against the Oracle's in each direction, and ST (trained forward) on the backward one;
    a dashed line marks the random policy's return."""
    directions = ("forward", "backward")  # env 0, env 1
    methods = [m for m in COLORS if select(rows, family="go1", method=m, metric="online_return_env0")]
    if not methods:
        return "go1: no Go1 Exp 1 runs"
    # random actions move Go1 backward, so the random policy's backward return is far from 0
    random_returns = [random_policy_return("go1", env) for env in range(len(directions))]
    fig, axes = plt.subplots(1, 2, figsize=(2.4 * len(methods) + 4, 3.5), sharey=True)
    width, shown = 0.8 / len(methods), []
    for ax, protocol, match, label in (
        (axes[0], "online", {}, "Exp 1, online"),
        (axes[1], "offline", {"x": 0}, "Exp 2, 0 steps (CLAW: one pass)"),
    ):
        for i, method in enumerate(methods):
            bars = [select(rows, family="go1", method=method, metric=f"{protocol}_return_env{env}", **match) for env in (0, 1)]
            bars = [b[0] for b in bars if b]
            shown += bars
            ax.bar(
                [env + (i - (len(methods) - 1) / 2) * width for env in range(len(bars))],
                [b["mean"] for b in bars],
                width,
                yerr=_yerr("return", bars),
                color=COLORS[method],
                label=LABELS[method],
                capsize=3,
            )
        ax.hlines(
            random_returns,
            [env - 0.45 for env in range(len(directions))],
            [env + 0.45 for env in range(len(directions))],
            color="gray",
            linestyle="--",
            label="random policy",
        )
        ax.set_xticks(range(len(directions)), directions)
        ax.set_title(label, fontsize="medium")
    axes[0].set_ylabel("episode return")
    axes[0].legend(fontsize="small")
    fig.suptitle(f"Go1, size {shown[0]['size']}, {_seeds(shown)}")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "go1.png"), dpi=120)
    return None


def figure_training(training, out) -> str | None:
    """One panel per (family, training environment): each method's mean training-episode return per step window,
    95% CI band, and the random policy's return."""
    panels = sorted({(r["family"], r["train_env"]) for r in training}, key=str)
    if not panels:
        return "training: no budget or Exp 1/2 runs"
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.5), squeeze=False)
    for ax, (family, env_id) in zip(axes[0], panels):
        points = [r for r in training if (r["family"], r["train_env"]) == (family, env_id)]
        for method in sorted({p["method"] for p in points}, key=list(COLORS).index):
            line = [p for p in points if p["method"] == method]
            x, y = [p["step"] for p in line], [p["mean"] for p in line]
            ax.plot(x, y, color=COLORS[method], label=f"{LABELS[method]} (seeds {line[0]['seeds']})")
            ax.fill_between(x, *_interval("return", line), color=COLORS[method], alpha=0.15)
        ax.axhline(points[0]["random_policy"], color="gray", linestyle="--", label="random policy")
        where = "all environments" if env_id == "all" else f"env {env_id}"
        ax.set(title=f"{family}, {where}, size {points[0]['size']}", xlabel="agent steps", ylabel="training-episode return")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda value, _: f"{value / 1000:g}k"))
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "training.png"), dpi=120)
    return None


def figure_controls(controls, out) -> str | None:
    """Per trained method and family: returns with the own context vs another environment's (each protocol), and
    against context size."""
    panels = sorted({(r["method"], r["family"]) for r in controls})
    if not panels:
        return "controls: no finished controls runs"
    fig, axes = plt.subplots(2, len(panels), figsize=(4.5 * len(panels), 7), squeeze=False)
    for (top, bottom), (method, family) in zip(axes.T, panels):
        rows = [r for r in controls if (r["method"], r["family"]) == (method, family)]
        drops = [r for r in rows if r["arm"] == "own - another"]  # paired: same seeds and noise otherwise
        own = {r["protocol"]: r["mean"] for r in rows if r["arm"] == "own"}
        top.bar(
            [f"{r['protocol']}\n(own: {own[r['protocol']]:.0f})" for r in drops],
            [r["mean"] for r in drops],
            yerr=[_ci(r["ci95_pairs"]) for r in drops],
            color=COLORS[method],
            capsize=4,
        )
        top.axhline(0, color="gray", linewidth=0.8)
        top.set(
            title=f"{LABELS[method]}\n{family}, seeds {rows[0]['seeds']}\nown minus another environment's context",
            ylabel="return difference (95% CI, seed x env)",
        )
        sizes = sorted((r for r in rows if r["arm"] == "size"), key=lambda r: r["context_episodes"])
        episodes = [r["context_episodes"] for r in sizes]
        bottom.errorbar(
            episodes,
            [r["mean"] for r in sizes],
            yerr=_yerr("return", sizes, "ci95_seeds"),
            color=COLORS[method],
            marker="o",
            capsize=4,
        )
        bottom.set(
            xscale="log",
            xlabel="pi_con episodes in the context",
            ylabel="offline return (95% CI, seeds)",
            title=f"{family}: context size",
        )
        bottom.set_xticks(episodes, [str(k) for k in episodes])
    fig.tight_layout()
    fig.savefig(os.path.join(out, "controls.png"), dpi=120)
    return None


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "roots",
        nargs="+",
        metavar="root",
        help="sweep directories or archives (experiments/archive.py), e.g. runs/sweeps/cpu results/learn/runs",
    )
    parser.add_argument("--out", default=None, help="output directory (default: the first root)")
    cli = parser.parse_args(argv)
    check_roots("figures.py", cli.roots)
    out = cli.out or cli.roots[0]
    if os.path.exists(out) and not os.path.isdir(out):
        raise SystemExit(f"error: --out {out} is a file; figures.py writes its PNGs into a directory")
    runs, _ = load_sweep("figures.py", cli.roots)
    os.makedirs(out, exist_ok=True)
    rows, curves, problems = summarize(runs)
    for dir_, why in problems:  # the damaged ones were named as they were read
        print(f"not aggregated: {os.path.basename(dir_)}: {why}")
    for figure in (figure_exp1, figure_exp2, figure_exp3, figure_exp4, figure_exp5, figure_go1):
        skipped = figure(rows, curves, out)
        print(f"skipped {skipped}" if skipped else f"wrote {os.path.join(out, figure.__name__[7:] + '.png')}")
    skipped = figure_training(training_curves(runs), out)
    print(f"skipped {skipped}" if skipped else f"wrote {os.path.join(out, 'training.png')}")
    skipped = figure_controls(controls_rows(runs), out)
    print(f"skipped {skipped}" if skipped else f"wrote {os.path.join(out, 'controls.png')}")


if __name__ == "__main__":
    main()
