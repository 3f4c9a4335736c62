"""The reports' section "Does the learner see its crash coming": the numbers each evaluation
recorded (``eval.json``'s ``crash_sight``, :mod:`memrl.evaluation.crash_sight`) as markdown,
one line per Table III row and initial-lane setting, pooled over the row's units.

In every evaluation folder's ``eval.md`` (:func:`evaluation_markdown`), in ``memrl.report``'s
``table3.md`` and in the study's ``report.md`` (:func:`sight_section`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from memrl.evaluation import stats
from memrl.evaluation.crash_sight import BINS, SPEED, bin_name, pool
from memrl.evaluation.results import EvalResult

TITLE = "## Does the learner see its crash coming"
LANE_NAMES = {"random": "random", "non_goal": "non-goal"}
Q_KINDS = ("checkpoint", "stage1")
"""``meta.kind`` of the evaluations of a Q-network (the ones that record the section)."""
DASH = "\u2014"


def _num(x: float | None, digits: int = 1) -> str:
    return DASH if x is None else f"{x:.{digits}f}"


def _gamma(g: float) -> str:
    return f"{g:g}"


def _pooled(results: Sequence[EvalResult]) -> list[tuple[str, dict[str, Any], float]]:
    """Per initial-lane setting (protocol order) of the units that recorded it: the pooled block
    and the discount."""
    recorded = [r for r in results if r.crash_sight]
    lanes: list[str] = []
    for r in recorded:
        lanes += [lane for lane in r.crash_sight["lanes"] if lane not in lanes]  # type: ignore[index]
    out = []
    for lane in lanes:
        blocks = [r.crash_sight["lanes"][lane] for r in recorded  # type: ignore[index]
                  if lane in r.crash_sight["lanes"]]  # type: ignore[index]
        out.append((lane, pool(blocks), float(recorded[0].crash_sight["gamma"])))  # type: ignore[index]
    return out


def _cell(row: dict[str, Any], key: str = "") -> str:
    if not row["n"]:
        return DASH
    if key:
        return _num(row.get(key), 2)
    return f"{_num(row['q'])} / {_num(row['g'])}"


def _pcts(values: list[float] | None) -> str:
    return DASH if not values else " / ".join(f"{v:.2f}" for v in values)


def _shares(counts: dict[str, int] | None) -> str:
    if not counts or not sum(counts.values()):
        return DASH
    total = sum(counts.values())
    return " / ".join(f"{counts[k] / total:.2f}" for k in SPEED)


def sight_lines(rows: Sequence[tuple[str, Sequence[EvalResult]]]) -> list[str]:
    """The section for ``rows`` (label, the row's evaluations), always with its heading: the
    tables of the rows whose evaluations recorded it, and which did not."""
    pooled = [(label, lane, block, gamma)
              for label, results in rows for lane, block, gamma in _pooled(results)]
    missing = [label for label, results in rows if not any(r.crash_sight for r in results)
               and any(r.meta.get("kind") in Q_KINDS for r in results)]
    lines = [TITLE, ""]
    if not pooled:
        lines.append("No evaluation here recorded its Q-values: only a Q-network's protocol evaluation "
                     "does (not the scripted driver, random, a person or another library's agent)"
                     + (f"; {', '.join(missing)} were evaluated before they were recorded (evaluate again "
                        "with `overwrite=true`)." if missing else "."))
        return [*lines, ""]
    first = next(r for _, results in rows for r in results if r.crash_sight)
    sight: dict[str, Any] = first.crash_sight  # type: ignore[assignment]
    duration, kept = int(sight["duration"]), int(sight["survivor_steps"])
    gammas = sorted({g for *_, g in pooled})
    gamma_words = f"gamma = {_gamma(gammas[0])}" if len(gammas) == 1 else \
        "gamma of each run's config (in the row)"

    def label_of(label: str, gamma: float) -> str:
        return label if len(gammas) == 1 else f"{label} (gamma {_gamma(gamma)})"

    bins = [bin_name(lo, hi) for lo, hi in BINS]
    heads = ["1 step before", *bins[1:]]
    lines += [
        "On each evaluation's own test episodes (the greedy episodes the scores above count, recorded "
        "as they were driven), with the evaluated weights; the network's expected Q-values (a "
        "distributional head's mean). Pooled over the row's units.", "",
        "**Q against the return, by steps before a crash.** Mean Q(s_t, a_t) of the action taken / mean "
        f"discounted return that followed, G_t = sum_k gamma^k r_(t+k) ({gamma_words}; a crash ends the "
        "sum), over the steps that many steps before a crash (1: the step whose action ended in the "
        f"crash), and over the survivors' steps 1\u2013{kept} (of {duration}: the sum cut by the time "
        "limit misses at most gamma^"
        f"{duration - kept} of the rest). A learner that sees its crashes coming has Q near G on the "
        "steps before them; one that does not values them like the survivors' steps. Crashes: the "
        "crashed episodes (per unit).", "",
        "| row | starts | episodes | crashes | " + " | ".join(heads)
        + f" | survivors (steps 1\u2013{kept}) |",
        "|---|---|---|---|" + "---|" * (len(heads) + 1)]
    for label, lane, block, gamma in pooled:
        per = f" ({', '.join(map(str, block['crashes_per_unit']))})" if block["units"] > 1 else ""
        cells = [_cell(row) for row in block["calibration"]]
        lines.append(f"| {label_of(label, gamma)} | {LANE_NAMES.get(lane, lane)} | {block['episodes']} | "
                     f"{block['crashes']}{per} | " + " | ".join(cells) + " |")
    if any("q_risk" in row for *_, block, _ in pooled for row in block["calibration"]):
        lines += ["", "**q_risk, by steps before a crash.** The mean of the network's `risk` output for "
                  "the action taken (a crash-risk head's estimate of a crash ahead), over the same steps; "
                  f"{DASH}: no risk output or no such steps.", "",
                  "| row | starts | " + " | ".join(heads) + f" | survivors (steps 1\u2013{kept}) |",
                  "|---|---|" + "---|" * (len(heads) + 1)]
        for label, lane, block, gamma in pooled:
            lines.append(f"| {label_of(label, gamma)} | {LANE_NAMES.get(lane, lane)} | "
                         + " | ".join(_cell(row, "q_risk") for row in block["calibration"]) + " |")
    if any("masked" in row for *_, block, _ in pooled for row in block["calibration"]):
        lines += ["", "**The mask's share, by steps before a crash.** The share of those steps whose action "
                  "taken is not the task head's greedy action (argmax Q): where the crash-risk critic's "
                  f"mask chose another; {DASH}: no such steps.", "",
                  "| row | starts | " + " | ".join(heads) + f" | survivors (steps 1\u2013{kept}) |",
                  "|---|---|" + "---|" * (len(heads) + 1)]
        for label, lane, block, gamma in pooled:
            lines.append(f"| {label_of(label, gamma)} | {LANE_NAMES.get(lane, lane)} | "
                         + " | ".join(_cell(row, "masked") for row in block["calibration"]) + " |")
    lines += _risk_lines(pooled, label_of)
    lines += [
        "", "**The action gap beside the fit's error.** Percentiles 10 / 50 / 90 over every test state: "
        "best \u2212 second (the greedy action's Q minus the next best of the 9), speed gap (max \u2212 min "
        "of Q over the three speed changes at the greedy curvature change), curvature gap (over the three "
        "curvature changes at the greedy speed change); the shares of states whose greedy action slows "
        "down, keeps the speed, speeds up; mean Q over states and actions. TD error: mean "
        "|Q(s, a) \u2212 (r + gamma max_a' Q(s', a'))| over the same test steps, the evaluated weights on "
        "both sides (no target network), a crash's target its reward alone, the last step of an episode "
        "cut by the time limit left out: the fit's one-step error on the test episodes the policy drove, "
        "not on the replay buffer. Where the gaps lie below the TD error, the choice between those "
        "actions is the fit's error's. Several units: each percentile the mean of the units' (states "
        "and shares pooled).", "",
        "| row | starts | states | best \u2212 second | speed gap | curvature gap | greedy slower / keep / "
        "faster | mean Q | TD error (steps) |", "|---|---|---|---|---|---|---|---|---|"]
    for label, lane, block, gamma in pooled:
        g = block["gaps"]
        lines.append(f"| {label_of(label, gamma)} | {LANE_NAMES.get(lane, lane)} | {g['states']:,} | "
                     f"{_pcts(g['best_second'])} | {_pcts(g['speed_gap'])} | {_pcts(g['curvature_gap'])} | "
                     f"{_shares(g['greedy_speed'])} | {_num(g['mean_q'], 2)} | {_num(g['td'], 2)} "
                     f"({g['td_n']:,}) |")
    if missing:
        lines += ["", f"Not recorded: {', '.join(missing)} (evaluated before Q-values were recorded; "
                  "evaluate again with `overwrite=true`)."]
    return [*lines, ""]


def _risk_cell(row: dict[str, Any]) -> str:
    if not row["n"]:
        return DASH
    return (f"{_num(row['predicted'], 3)} / {_num(row['realized'], 3)} / {_num(row['within'], 2)} "
            f"({row['n']:,})")


def _risk_lines(pooled: Sequence[tuple[str, str, dict[str, Any], float]], label_of: Any) -> list[str]:
    """The risk calibration table of the rows whose network has a crash-risk head."""
    risky = [p for p in pooled if "risk_calibration" in p[2]]
    if not risky:
        return []
    bins = [row["risk"] for row in risky[0][2]["risk_calibration"]]
    return ["", "**The crash-risk head's calibration.** Test steps grouped by the predicted risk of the "
            "action taken; per group: mean predicted risk / mean realized gamma_risk^k (k: steps from "
            "the step's action to the crash that followed; 0 for none: what the critic estimates) / the "
            "share of steps with a crash within the critic's horizon 1 / (1 \u2212 gamma_risk) (steps). "
            "Every step of a crashed episode; the survivors' steps far from the time limit, as above. "
            "A calibrated critic has predicted = realized in every group.", "",
            "| row | starts | " + " | ".join(f"risk {b}" for b in bins) + " |",
            "|---|---|" + "---|" * len(bins),
            *(f"| {label_of(label, gamma)} | {LANE_NAMES.get(lane, lane)} | "
              + " | ".join(_risk_cell(row) for row in block["risk_calibration"]) + " |"
              for label, lane, block, gamma in risky)]


def sight_section(groups: Sequence[Sequence[EvalResult]], cfg: stats.StatsConfig) -> list[str]:
    """The section for the reports: per Table III row (each of ``groups`` split into rows as the
    table is)."""
    return sight_lines([(g.label, g.results) for results in groups for g in stats.rows_of(results, cfg)])


def evaluation_markdown(result: EvalResult) -> str:
    """An evaluation folder's ``eval.md``: its scores and the section."""
    lines = [f"# Evaluation: {result.name} [{result.unit}]", "",
             "| starts | episodes | survival | goal |", "|---|---|---|---|"]
    lines += [f"| {LANE_NAMES.get(lane, lane)} | {s.episodes} | {s.survival_score:.0f} | {s.goal_score:.0f} |"
              for lane, s in result.scores.items()]
    return "\n".join([*lines, "", *sight_lines([(result.name, [result])])])
