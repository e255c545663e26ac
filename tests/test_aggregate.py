"""aggregate.py on synthetic runs with known answers: claim verdicts, context-control tables, training curves."""

import json
import math

import pytest
import scipy.stats

from common.evaluation import mean_ci
from experiments import aggregate, figures


def fake_run(method, family, seed, scalars, size="F", rank=16):
    return {
        "dir": f"/nonexistent/{method}{family}{size}{rank}{seed}",
        "method": method,
        "family": family,
        "size": size,
        "rank": rank,
        "seed": seed,
        "status": "done",
        "experiments": [],
        "scalars": scalars,
    }


def online(values):
    return {"eval/online/episodic_return": [(100, values)]}


def verdicts(runs, **kwargs):
    results = aggregate.claims(aggregate.seed_values(aggregate.group_runs(runs)[0]), **kwargs)
    return {r["claim"].split(" (")[0]: r for r in results}


def test_exp1_claim_follows_welch_intervals_and_the_oracle_margin():
    returns = {"claw": [100.0, 104.0, 108.0], "dr": [50.0, 55.0, 52.0], "oracle": [101.0, 106.0, 107.0]}
    runs = [fake_run(m, "reach", seed, online(v)) for m, vs in returns.items() for seed, v in enumerate(vs, 1)]
    missing = verdicts(runs)["CLAW tracks the oracle and beats DR and ST online"]
    assert missing["verdict"] == "runs missing" and any("CLAW - ST: runs missing" in e for e in missing["evidence"])

    def claim(st_returns):
        more = [fake_run("st", "reach", seed, online(v)) for seed, v in enumerate(st_returns, 1)]
        return verdicts(runs + more)["CLAW tracks the oracle and beats DR and ST online"]

    beaten = claim([60.0, 62.0, 58.0])
    assert beaten["verdict"] == "reproduced"
    low, high = scipy.stats.ttest_ind(returns["claw"], returns["dr"], equal_var=False).confidence_interval(0.95)
    assert f"CLAW - DR: +51.7 [{low:+.1f}, {high:+.1f}] (n = 3 vs 3): supports" in beaten["evidence"][0]
    assert beaten["evidence"][2].endswith("margin 10.5): supports")  # within 10% of the oracle's 104.7
    assert claim([200.0, 210.0, 205.0])["verdict"] == "not reproduced"  # ST clearly better
    assert claim([40.0, 100.0, 170.0])["verdict"] == "not separable at n = 3"


def test_a_family_with_runs_missing_is_named_and_left_out_of_the_verdict():
    returns = {
        "claw": [100.0, 104.0, 108.0],
        "dr": [50.0, 55.0, 52.0],
        "st": [60.0, 62.0, 58.0],
        "oracle": [101.0, 106.0, 107.0],
    }
    reach = [fake_run(m, "reach", seed, online(v)) for m, vs in returns.items() for seed, v in enumerate(vs, 1)]
    push = [fake_run(m, "push", 1, online(vs[0])) for m, vs in returns.items()]  # one seed so far
    claim = verdicts(reach + push)["CLAW tracks the oracle and beats DR and ST online"]
    assert claim["verdict"] == "reproduced"  # reach decides; push is not tested yet
    assert claim["evidence"][0] == "by family: push runs missing; reach reproduced"
    assert "push Exp 1 return, CLAW - DR: runs missing (1 vs 1 seeds)" in claim["evidence"]
    # a contradiction in a complete family decides, whatever the other family lacks
    worse = [fake_run("st", "walker", s, online(500.0 + s)) for s in (1, 2, 3)]
    worse += [fake_run(m, "walker", s, online(vs[s - 1])) for m, vs in returns.items() if m != "st" for s in (1, 2, 3)]
    claim = verdicts(reach + push + worse)["CLAW tracks the oracle and beats DR and ST online"]
    assert claim["verdict"] == "not reproduced"
    assert claim["evidence"][0] == "by family: push runs missing; reach reproduced; walker not reproduced"
    alone = verdicts(push)["CLAW tracks the oracle and beats DR and ST online"]
    assert alone["verdict"] == "runs missing" and not alone["evidence"][0].startswith("by family")


def test_go1_claim_compares_each_direction_with_the_oracle():
    def directions(forward, backward):
        return {"eval/online/env0/episodic_return": [(100, forward)], "eval/online/env1/episodic_return": [(100, backward)]}

    runs = [fake_run("oracle", "go1", s, directions(300.0 + s, 280.0 - s)) for s in (1, 2, 3)]
    runs += [fake_run("dr", "go1", s, directions(150.0 + 2 * s, 140.0 + s)) for s in (1, 2, 3)]
    claim = verdicts(runs)["DR is good at neither Go1 direction and ST does not close the backward gap"]
    assert claim["verdict"] == "runs missing" and claim["evidence"][2].endswith("runs missing (3 vs 0 seeds)")
    st = [fake_run("st", "go1", s, directions(310.0, 60.0 + 5 * s)) for s in (1, 2, 3)]
    claim = verdicts(runs + st)["DR is good at neither Go1 direction and ST does not close the backward gap"]
    assert claim["verdict"] == "reproduced"
    assert [line.split(":")[0] for line in claim["evidence"]] == [
        "go1 forward Exp 1 return, Oracle - DR",
        "go1 backward Exp 1 return, Oracle - DR",
        "go1 backward Exp 1 return, Oracle - ST",
    ]
    closed = [fake_run("st", "go1", s, directions(310.0, 300.0 + s)) for s in (1, 2, 3)]  # ST beats the backward oracle
    claim = verdicts(runs + closed)["DR is good at neither Go1 direction and ST does not close the backward gap"]
    assert claim["verdict"] == "not reproduced"


def test_offline_returns_per_environment_only_where_a_family_has_two():
    def sweep(n_envs):
        scalars = {"eval/offline/episodic_return": [(0, 5.0), (10, 6.0)]}
        for j in range(n_envs):
            scalars[f"eval/online/env{j}/episodic_return"] = [(100, 10.0 * j), (200, 10.0 * j + 2)]
            scalars[f"eval/offline/env{j}/episodic_return"] = [(0, float(j)), (10, j + 0.5)]
        return aggregate.run_metrics(fake_run("dr", "go1", 1, scalars))

    two = sweep(2)
    assert two[("offline_return_env1", 0)] == 1.0 and two[("offline_return_env1", 10)] == 1.5
    assert two[("online_return_env1", None)] == 11.0 and two[("offline_return", 10)] == 6.0
    six = sweep(6)  # Reach's six goals: online per goal, offline only the family mean
    assert ("online_return_env5", None) in six and not any(k.startswith("offline_return_env") for k, _ in six)


def test_go1_figure_draws_each_method_per_direction(tmp_path, monkeypatch):
    def directions(forward, backward):
        return {
            "eval/online/env0/episodic_return": [(100, forward)],
            "eval/online/env1/episodic_return": [(100, backward)],
            "eval/offline/env0/episodic_return": [(0, forward / 2), (10, 0.0)],
            "eval/offline/env1/episodic_return": [(0, backward / 2), (10, 0.0)],
        }

    runs = [
        fake_run(m, "go1", s, directions(100.0 * k + s, 50.0 * k - s))
        for k, m in enumerate(("dr", "oracle"), 1)
        for s in (1, 2)
    ]
    rows, curves, _ = aggregate.summarize(runs)
    saved = []
    monkeypatch.setattr(figures.plt.Figure, "savefig", lambda fig, path, **kwargs: saved.append(fig))
    monkeypatch.setattr(figures, "random_policy_return", lambda family, env_id: {0: 5.0, 1: 50.0}[env_id])  # no rollout
    assert figures.figure_go1(rows, curves, str(tmp_path)) is None
    online_ax, offline_ax = saved[0].axes
    for ax, scale in ((online_ax, 1.0), (offline_ax, 0.5)):  # the offline panel: the sweep's 0-step point
        (random_line,) = [c for c in ax.collections if c.get_label() == "random policy"]
        assert [round(float(seg[0][1]), 1) for seg in random_line.get_segments()] == [5.0, 50.0]
        heights = {
            c.get_label(): [round(p.get_height(), 2) for p in c.patches]
            for c in ax.containers
            if c.get_label() in ("DR", "Oracle")
        }
        assert heights == {"DR": [101.5 * scale, 48.5 * scale], "Oracle": [201.5 * scale, 98.5 * scale]}
        assert [t.get_text() for t in ax.get_xticklabels()] == ["forward", "backward"]
    assert figures.figure_go1(aggregate.summarize(runs[:0])[0], [], str(tmp_path)) == "go1: no Go1 Exp 1 runs"


def test_exp2_collapse_is_paired_against_the_best_earlier_sweep_point():
    def sweep(values):  # x = 0, 10, 1000 offline steps
        return {"eval/offline/episodic_return": [(0, values[0]), (10, values[1]), (1000, values[2])]}

    runs = [fake_run("claw", "walker", s, {"eval/offline/episodic_return": [(0, 300.0 + s)]}) for s in (1, 2, 3)]
    runs += [fake_run("dr", "walker", s, sweep([200.0 + s, 250.0 + 2 * s, 100.0 + s])) for s in (1, 2, 3)]
    runs += [fake_run("st", "walker", s, sweep([150.0, 160.0 + s, 170.0 + 3 * s])) for s in (1, 2, 3)]
    runs += [fake_run("oracle", "walker", s, sweep([400.0, 420.0 + s, 200.0 * s])) for s in (1, 2, 3)]
    claim = verdicts(runs)["Gradient methods collapse with many offline steps, CLAW does not"]
    lines = {line.split(":")[0]: line for line in claim["evidence"]}
    dr = lines["walker Exp 2 DR collapses"]
    assert (
        "return at 10 steps (its best before 1000) - at 1000" in dr and "paired over 3 seeds" in dr and dr.endswith("supports")
    )
    mean, half = mean_ci([150.0 + s for s in (1, 2, 3)])
    assert f"+{mean:.1f} [{mean - half:+.1f}, {mean + half:+.1f}]" in dr
    assert lines["walker Exp 2 ST collapses"].endswith("contradicts")  # ST improves with steps here
    assert lines["walker Exp 2 CLAW (one pass) - DR at 1000 steps"].endswith("supports")
    assert claim["verdict"] == "not reproduced"

    # seeds 1-2 measured the 10-step point, seeds 3-4 the 1000-step point: nothing to pair
    split = [
        fake_run(
            "dr", "reach", s, {"eval/offline/episodic_return": [(0, 100.0), (10 if s < 3 else 1000, 200.0 if s < 3 else 50.0)]}
        )
        for s in (1, 2, 3, 4)
    ]
    evidence = verdicts(split)["Gradient methods collapse with many offline steps, CLAW does not"]["evidence"]
    assert (
        "reach Exp 2 DR collapses: return at 10 steps (its best before 1000) - at 1000: runs missing (0 seed(s) with both values)"
        in evidence
    )


def test_rank_slope_and_exp5_posthoc_comparison():
    runs = [
        fake_run(
            "claw",
            "cheetah_walker",
            s,
            {**online(50.0 * r.bit_length() + s), "eval/online/env0/episodic_return": [(100, 80.0 + s)]},
            rank=r,
        )
        for r in (1, 4, 8, 16)
        for s in (1, 2, 3)
    ]
    runs += [
        fake_run("posthoc", "cheetah_walker", s, {"eval/online/env0/episodic_return": [(100, 80.0 + 2 * s - 1)]}, rank=8)
        for s in (1, 2, 3)
    ]
    runs += [fake_run(m, "cheetah_walker", s, online(10.0 * s), rank=8) for m in ("film", "concat") for s in (1, 2, 3)]
    claims = verdicts(runs)
    slope = claims["Return rises with LoRA rank"]
    assert (
        slope["verdict"] == "reproduced"
        and "ranks [1, 4, 8, 16]" in slope["evidence"][0]
        and "+50.0 [" in slope["evidence"][0]
    )
    assert claims["CLAW beats FiLM and Concat at mid sizes"]["verdict"] == "reproduced"
    assert claims["Joint training beats the post-hoc hypernetwork"]["verdict"] == "not separable at n = 3"
    assert verdicts(runs, exp4_size="H", exp4_rank=2)["Return rises with LoRA rank"]["verdict"] == "runs missing"


def test_controls_rows_average_environments_per_seed_then_across_seeds(tmp_path):
    runs = []
    for seed in (1, 2, 3):
        own = {str(e): 100.0 + 10 * e + seed for e in range(3)}
        swapped = {str(e): 90.0 + 10 * e for e in range(3)}
        result = {
            "family": "reach",
            "n_envs": 3,
            "context_episodes": 3,
            "swap_offset": 1,
            "eval_episodes": 2,
            "online_eval_steps": 0,
            "swap": {"own": {"offline": own}, "swapped": {"offline": swapped}},
            "size": {"1": swapped, "10": own},
        }
        run_dir = tmp_path / f"controls{seed}"
        run_dir.mkdir()
        (run_dir / "controls.json").write_text(json.dumps(result))
        runs.append(
            {
                "dir": str(run_dir),
                "method": "controls",
                "family": "reach",
                "size": "F",
                "rank": 16,
                "seed": seed,
                "status": "done",
                "experiments": ["controls"],
                "scalars": {},
            }
        )
    assert aggregate.problem(runs[0]) == "context controls (evaluation only), in controls.md"
    # the decoder runs' controls: a group of their own, whatever their numbers
    runs.append({**runs[0], "method": "controls_decoder", "experiments": ["decoder"]})
    assert aggregate.problem(runs[-1]) == "context controls (evaluation only), in controls.md"
    decoder_rows = [r for r in aggregate.controls_rows(runs) if r["method"] == "claw_decoder"]
    assert len(decoder_rows) == 5 and all(r["n_seeds"] == 1 and r["seeds"] == "1" for r in decoder_rows)
    one_seed = aggregate.controls_markdown(decoder_rows)  # one seed: no interval across seeds, one across its environments
    assert "nan" not in one_seed and "| none (one sample) | 3 | ± " in one_seed
    figures.figure_controls(aggregate.controls_rows(runs), str(tmp_path))  # a column per (trained method, family)
    assert (tmp_path / "controls.png").stat().st_size > 0
    runs.pop()
    assert {r["method"] for r in aggregate.controls_rows(runs)} == {"claw"}
    rows = {r["quantity"]: r for r in aggregate.controls_rows(runs)}
    drop = rows["offline: own - another's"]
    assert drop["mean"] == pytest.approx(12.0) and drop["ci95_seeds"] == pytest.approx(mean_ci([11.0, 12.0, 13.0])[1])
    assert drop["n_pairs"] == 9 and drop["ci95_pairs"] == pytest.approx(
        mean_ci([10.0 + s for s in (1, 2, 3) for _ in range(3)])[1]
    )
    assert list(rows)[-2:] == ["offline: 1-episode own context", "offline: 10-episode own context"]
    assert rows["offline: own context (3 episodes)"]["mean"] == pytest.approx(112.0)
    assert "| claw | reach | F | 16 | offline: own - another's | 3 | 12.0 |" in aggregate.controls_markdown(
        aggregate.controls_rows(runs)
    )
    assert figures.figure_controls([], str(tmp_path)) == "controls: no finished controls runs"
    assert (
        figures.figure_controls(aggregate.controls_rows(runs), str(tmp_path)) is None
        and (tmp_path / "controls.png").stat().st_size > 0
    )


def test_exp12_runs_have_training_curves_per_method_beside_the_budget_runs(tmp_path, monkeypatch):
    monkeypatch.setattr(aggregate, "random_policy_return", lambda family, env_id: 5.0 if env_id == "all" else 4.0)

    def run(method, seed, returns, successes=(), experiments=("exp1", "exp2")):
        return {
            "method": method,
            "family": "reach",
            "size": "F",
            "seed": seed,
            "experiments": list(experiments),
            "command": f"python {method}_tdmpc2.py --family reach",
            "scalars": {"charts/episodic_return": returns, "charts/episodic_success": list(successes)},
        }

    runs = [run("st", s, [(2500, 10.0 * s)]) for s in (1, 2)]
    runs += [run("dr", 1, [(1000, 90.0), (2000, 110.0), (4000, 50.0)], [(1000, 0.0), (2000, 1.0), (4000, 1.0)])]
    runs += [
        run("oracle", 1, [(2500, 7.0)], experiments=("exp4",)),
        run("controls", 1, [(2500, 1.0)], experiments=("controls",)),
    ]
    rows = aggregate.training_curves(runs)
    assert [(r["method"], r["train_env"], r["step"], r["n"], r["mean"], r["random_policy"]) for r in rows] == [
        ("dr", "all", 2500, 1, 100.0, 5.0),
        ("dr", "all", 5000, 1, 50.0, 5.0),
        ("st", 0, 2500, 2, 15.0, 4.0),
    ]
    assert [r["success"] for r in rows[:2]] == [0.5, 1.0] and math.isnan(rows[2]["success"])
    table = aggregate.training_markdown(rows)
    assert "| dr | reach | all | F | 2500 | 1 | 100.0 | none (one sample) | 20.0 (random 5.0) | 0.50 |" in table
    assert table.rstrip().endswith("| 3.8 (random 4.0) |  |")
    assert figures.figure_training(rows, str(tmp_path)) is None and (tmp_path / "training.png").stat().st_size > 0
    assert figures.figure_training([], str(tmp_path)) == "training: no budget or Exp 1/2 runs"


def test_panel_grid_legend_lists_every_method_of_every_panel(tmp_path, monkeypatch):
    methods = {"reach": ["claw", "oracle"], "walker": ["claw", "dr"]}  # the last panel alone lacks the oracle

    def draw(ax, family, metric):
        for i, method in enumerate(methods[family]):
            ax.plot([0, 1], [i, i], label=method)

    saved = []
    monkeypatch.setattr(figures.plt.Figure, "savefig", lambda fig, path, **kwargs: saved.append(fig))
    figures.save_panel_grid(["reach", "walker"], "online", draw, str(tmp_path / "grid.png"))
    legend = saved[0].legends[0]
    assert [text.get_text() for text in legend.get_texts()] == ["claw", "oracle", "dr"]


def test_exp4_title_counts_the_seeds_of_the_methods_it_draws(tmp_path, monkeypatch):
    def row(method, rank, n):
        return {
            "method": method,
            "family": "cheetah_walker",
            "size": "F",
            "rank": rank,
            "metric": "online_return",
            "mean": 150.0,
            "n": n,
            "ci95": 20.0,
        }

    rows = [row("claw", 1, 2), row("claw", 4, 2), row("film", 8, 2), row("concat", 8, 2), row("posthoc", 8, 1)]
    saved = []
    monkeypatch.setattr(figures.plt.Figure, "savefig", lambda fig, path, **kwargs: saved.append(fig))
    assert figures.figure_exp4(rows, [], str(tmp_path)) is None
    assert saved[0].axes[0].get_title() == "Cheetah/Walker, size F, n = 2"  # post-hoc's one seed is Exp 5's, not drawn here
