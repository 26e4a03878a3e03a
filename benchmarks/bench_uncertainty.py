"""Benchmark: cost per decision of the uncertainty estimators, one batched pass vs a Python loop of K passes.

    python benchmarks/bench_uncertainty.py            # full run (about a minute on a laptop CPU)
    python benchmarks/bench_uncertainty.py --quick    # fewer repeats, no 5-human ensemble rows

What is measured (torch on ONE intra-op thread, `torch.set_num_threads(1)`; CPU):

* MC-dropout, K = 20, the default odv-ppo-drop network (LSTM 2 x 64, actor 2 x 128), untrained (timing does not
  depend on the weights), on observations of `position_swap` with 1 and with 5 humans, batch B = 1 and 64:
  - batched: `MCDropoutEstimator(policy, k=20)(obs)`, the shipped path: the batch repeated K times, ONE pass;
  - loop: the same estimator pipeline with K sequential `action_stats` passes over the B rows (inside one
    `mc_dropout` context), then the same statistics.
* Deep ensemble, K = 20 members of that network: `EnsembleEstimator(members)` (stacked: `vmap` over the stacked
  weights) vs `EnsembleEstimator(members, stacked=False)` (a loop over the members).

"per decision" = per observation that receives an estimate = (time per call) / B. The median over repeats is
reported (the machine may be shared). Targets (MC, the shipped path): <= 1 ms per decision at B = 1 and >= 5x faster
than the loop at B = 1; at B = 64 the loop's passes are themselves batched over 64 rows, so the speed-up there is
reported, and only the per-decision target applies.
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / torch load

_bench.single_thread()

import argparse  # noqa: E402
import os  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

import socnav  # noqa: E402
from socnav.rl import make_model  # noqa: E402
from socnav.uncertainty import EnsembleEstimator, MCDropoutEstimator, Uncertainty, feature_uncertainty  # noqa: E402
from socnav.uncertainty.estimators import obs_to_tensors, summarise_samples  # noqa: E402

K = 20
TARGET_US_PER_DECISION = 1000.0
TARGET_SPEEDUP = 5.0


def mc_loop(estimator: MCDropoutEstimator, obs: dict[str, np.ndarray]) -> Uncertainty:
    """The MC-dropout estimate with K sequential passes (the comparison point; same statistics as the estimator)."""
    policy = estimator.policy
    tensors = obs_to_tensors(policy, obs)
    with policy.mc_dropout(estimator.p_test):
        samples = [policy.action_stats(tensors) for _ in range(estimator.k)]
    h, mu, log_std = (th.stack(t) for t in zip(*samples, strict=True))
    mean, u_ep, u_al, feat_var = summarise_samples(mu, log_std, h)
    return Uncertainty(mean, u_ep, u_al, feature_uncertainty(feat_var, *policy.feature_range))


def observations(n_humans: int, batch: int) -> dict[str, np.ndarray]:
    env = socnav.make_vec_env({"scenario": "position_swap", "n_humans": n_humans}, n_envs=batch)
    obs = env.reset()
    env.close()
    return obs  # type: ignore[return-value]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats, skip the 5-human ensemble rows")
    parser.add_argument("--repeats", type=int, default=None, help="timed blocks per measurement (median)")
    args = parser.parse_args()
    repeats = args.repeats or (3 if args.quick else 5)
    min_time = 0.1 if args.quick else 0.25
    th.set_num_threads(1)
    warnings.simplefilter("ignore", RuntimeWarning)  # untracked feature range of the untrained networks

    console = Console(width=150)
    console.print(
        f"torch {th.__version__}, {th.get_num_threads()} intra-op thread, K = {K}, "
        f"median of {repeats} blocks, os.cpu_count() = {os.cpu_count()}"
    )
    env = socnav.make_vec_env({"scenario": "position_swap", "n_humans": 1}, n_envs=1)
    policies = [make_model("odv-ppo-drop", env, seed=seed).policy for seed in range(K)]
    th.set_num_threads(1)  # make_model sets the preset's torch_threads; keep it explicit
    policy = policies[0]
    with th.no_grad():  # a tracked feature range, so that u_feat is computed as in deployment
        h, _, _ = policy.action_stats(observations(5, 64))
        policy.features_extractor.update_feature_range(h - 1.0)
        policy.features_extractor.update_feature_range(h + 1.0)
    mc = MCDropoutEstimator(policy, k=K)
    stacked, looped = EnsembleEstimator(policies), EnsembleEstimator(policies, stacked=False)

    table = Table(title=f"Uncertainty estimation cost per decision (K = {K}, 1 thread)")
    for column in ("estimator", "humans", "B", "batched µs/call", "batched µs/decision", "loop µs/call",
                   "loop µs/decision", "speed-up", "target", "result"):
        table.add_column(column, justify="left" if column in ("estimator", "target") else "right")

    rows = [("MC-dropout", n, b) for n in (1, 5) for b in (1, 64)]
    rows += [("ensemble", n, b) for n in ((1,) if args.quick else (1, 5)) for b in (1, 64)]
    for kind, n_humans, batch in rows:
        obs = observations(n_humans, batch)
        if kind == "MC-dropout":
            fast = _bench.time_call(lambda obs=obs: mc(obs), repeats, min_time)
            slow = _bench.time_call(lambda obs=obs: mc_loop(mc, obs), repeats, min_time)
            per_decision = fast / batch * 1e6
            speedup = slow / fast
            if batch == 1:
                target = f"≤{TARGET_US_PER_DECISION:.0f} µs/dec, ≥{TARGET_SPEEDUP:.0f}x"
                ok = per_decision <= TARGET_US_PER_DECISION and speedup >= TARGET_SPEEDUP
            else:
                target = f"≤{TARGET_US_PER_DECISION:.0f} µs/dec"
                ok = per_decision <= TARGET_US_PER_DECISION
            result = "[green]PASS[/]" if ok else "[red]FAIL[/]"
        else:
            fast = _bench.time_call(lambda obs=obs: stacked(obs), repeats, min_time)
            slow = _bench.time_call(lambda obs=obs: looped(obs), repeats, min_time)
            per_decision, speedup = fast / batch * 1e6, slow / fast
            target, result = "— (info)", "stacked" if stacked.stacked else "fell back to loop"
        table.add_row(
            kind, str(n_humans), str(batch), f"{fast * 1e6:,.0f}", f"{per_decision:,.1f}", f"{slow * 1e6:,.0f}",
            f"{slow / batch * 1e6:,.1f}", f"{speedup:.1f}x", target, result,
        )
    console.print(table)


if __name__ == "__main__":
    main()
