"""Behaviour cloning: a policy's starting point taught by a controller (the ORCA robot with the planner) before PPO
fine-tunes it, as DRL-VO starts from a supervised policy (docs/maps.md, "Learning among walls").

`collect_demonstrations` runs the teacher in a VecEnv and keeps every step of its finished episodes with the return
that followed it; `clone` fits the policy to them by maximum likelihood, and its value head to those returns, so
that PPO's first advantages are not measured against an untrained critic:

    L_mean = mean |mu(o) - a_teacher|^2                 (the deterministic action: supervised, as DRL-VO's start)
    L_std  = - mean log N(a_teacher; sg[mu(o)], sigma(o))  (the spread: what the mean misses, mean held fixed)
    L_V    = mean (V(o) - G)^2,   G_t = sum_k gamma^k r_{t+k}   (to the end of the teacher's episode)

The mean is fitted by squares, not by the likelihood: with a spread that depends on the observation, the likelihood
lets the network call the hard steps (the sharp turns) noise instead of learning them (Seitzer et al., ICLR 2022).

Written on SB3's own `evaluate_actions`, so any `ActorCriticPolicy` can be cloned; the `imitation` package (which
has BC) pins gymnasium 0.29 and stable-baselines3 2.2, older than socnav's.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch as th
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.vec_env import VecEnv

__all__ = ["Demonstrations", "Teacher", "clone", "collect_demonstrations", "track_feature_range"]


class Teacher(Protocol):
    """A controller with SB3's ``predict`` (the ORCA robot: `socnav.controllers.OrcaController`)."""

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]: ...


@dataclass
class Demonstrations:
    """Steps of a teacher's finished episodes: ``observations[key]`` (N, ...), ``actions`` (N, 2) in [-1, 1],
    ``returns`` (N,) the discounted return from each step to the end of its episode, ``outcomes`` (N,) how that
    episode ended (``goal``, ``collision``, ...)."""

    observations: dict[str, np.ndarray]
    actions: np.ndarray
    returns: np.ndarray
    outcomes: np.ndarray

    def __len__(self) -> int:
        return len(self.actions)

    @classmethod
    def concatenate(cls, parts: list[Demonstrations]) -> Demonstrations:
        """The steps of all `parts`, in order."""
        keys = parts[0].observations.keys()
        return cls({key: np.concatenate([part.observations[key] for part in parts]) for key in keys},
                   np.concatenate([part.actions for part in parts]), np.concatenate([part.returns for part in parts]),
                   np.concatenate([part.outcomes for part in parts]))


def _returns_to_go(rewards: list[float], gamma: float) -> np.ndarray:
    """``G_t = r_t + gamma G_{t+1}``, ``G`` after the last step 0 (the episode ended)."""
    returns = np.empty(len(rewards))
    following = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        following = rewards[t] + gamma * following
        returns[t] = following
    return returns


def collect_demonstrations(env: VecEnv, teacher: Teacher, steps: int, gamma: float = 0.99,
                           driver: Teacher | None = None) -> Demonstrations:
    """Run `teacher` in `env` (already seeded) for ``steps`` env-steps in all (rounded up to whole batches) and keep
    the steps of the episodes that ended, each with its return to go (an unfinished episode has no return yet).

    With a `driver` (DAgger, Ross et al. 2011: the policy being taught) the driver's actions move the robot and the
    teacher's actions at the states the driver reaches are kept: the states a cloned policy drifts into, labelled
    with what the teacher would do there; the returns and outcomes are the driver's episodes'.

    A teacher or driver with ``on_episode_start(envs)`` (the ORCA robot, which keeps each robot's path; the safety
    layer, which keeps per-environment state) is told which environments began a new episode."""
    if steps <= 0:
        raise ValueError(f"steps must be > 0, got {steps}")
    observation = env.reset()
    if not isinstance(observation, dict):
        raise TypeError("collect_demonstrations needs a VecEnv with a Dict observation space (socnav's)")
    n_envs = env.num_envs
    stored: dict[str, list[np.ndarray]] = {key: [] for key in observation}
    actions: list[np.ndarray] = []
    # per environment: the rows (into the lists above) and rewards of its running episode
    rows: list[list[int]] = [[] for _ in range(n_envs)]
    rewards: list[list[float]] = [[] for _ in range(n_envs)]
    kept: list[int] = []
    returns: list[np.ndarray] = []
    outcomes: list[str] = []
    actors: list[Any] = [teacher] if driver is None else [teacher, driver]
    listeners = [actor.on_episode_start for actor in actors if hasattr(actor, "on_episode_start")]
    for listener in listeners:
        listener(np.arange(n_envs))
    for _ in range(-(-steps // n_envs)):
        action = np.clip(np.asarray(teacher.predict(observation, deterministic=True)[0], dtype=np.float32), -1, 1)
        for key, value in observation.items():
            stored[key].append(np.asarray(value, dtype=np.float32))
        actions.append(action)
        if driver is not None:
            action = np.clip(np.asarray(driver.predict(observation, deterministic=True)[0], dtype=np.float32), -1, 1)
        base = (len(actions) - 1) * n_envs
        stepped, reward, done, infos = env.step(action)
        assert isinstance(stepped, dict)
        observation = stepped
        for index in range(n_envs):
            rows[index].append(base + index)
            rewards[index].append(float(reward[index]))
        ended = np.flatnonzero(done)
        for index in ended.tolist():
            kept.extend(rows[index])
            returns.append(_returns_to_go(rewards[index], gamma))
            outcomes.extend([str(infos[index].get("outcome", ""))] * len(rows[index]))
            rows[index], rewards[index] = [], []
        if len(ended):
            for listener in listeners:
                listener(ended)
    order = np.asarray(kept, dtype=np.int64)
    flat = {key: np.concatenate(values)[order] for key, values in stored.items()}
    flat_returns = np.concatenate(returns) if returns else np.zeros(0)
    return Demonstrations(flat, np.concatenate(actions)[order], flat_returns.astype(np.float32),
                          np.asarray(outcomes, dtype=str))


def _critic_parameters(policy: ActorCriticPolicy) -> list[th.nn.Parameter]:
    """The parameters only the value estimate uses (the critic's layers and head)."""
    return [*policy.mlp_extractor.value_net.parameters(), *policy.value_net.parameters()]


def clone(policy: ActorCriticPolicy, demonstrations: Demonstrations, epochs: int = 10, batch_size: int = 256,
          learning_rate: float = 1e-3, seed: int = 0,
          imitate: Collection[str] | None = None) -> list[dict[str, float]]:
    """Fit `policy` (in place) to the teacher: the action mean to its actions, the spread to what the mean misses,
    the critic to the returns (the three losses above), with Adam over shuffled minibatches; dropout stays on, as in
    training. The critic's loss trains only the critic's own layers: returns are tens of units where actions are
    within [-1, 1], and through the shared extractor they would drown the actions' gradient.

    :param imitate: the outcomes whose episodes' actions are imitated (e.g. ``{"goal"}``: the teacher's actions in
        the episodes where it collided are not taught); None imitates every step. The critic learns from all.
    :return: per epoch, the mean ``action_mse``, ``nll`` (-log pi with the mean held) and ``value_loss``.
    """
    if len(demonstrations) == 0:
        raise ValueError("no demonstrations: the teacher finished no episode; collect more steps")
    generator = np.random.default_rng(seed)
    critic = _critic_parameters(policy)
    critic_ids = {id(parameter) for parameter in critic}
    actor_optimizer = th.optim.Adam([p for p in policy.parameters() if id(p) not in critic_ids], lr=learning_rate)
    critic_optimizer = th.optim.Adam(critic, lr=learning_rate)
    observations = {key: th.as_tensor(value) for key, value in demonstrations.observations.items()}
    actions = th.as_tensor(demonstrations.actions)
    returns = th.as_tensor(demonstrations.returns)
    taught = th.as_tensor(np.ones(len(demonstrations), dtype=bool) if imitate is None
                          else np.isin(demonstrations.outcomes, list(imitate)))
    if not bool(taught.any()):
        raise ValueError(f"imitate={sorted(imitate or [])}: no demonstration ended so; the teacher's outcomes are "
                         f"{sorted(set(demonstrations.outcomes.tolist()))}")
    policy.set_training_mode(True)
    history = []
    for _ in range(epochs):
        totals = np.zeros(3)
        batches = 0
        for rows in np.array_split(generator.permutation(len(demonstrations)),
                                   max(1, len(demonstrations) // batch_size)):
            index = th.as_tensor(rows)
            batch = {key: value[index] for key, value in observations.items()}
            weight = taught[index].to(actions.dtype)
            count = weight.sum().clamp(min=1.0)
            features = policy.extract_features(batch)
            assert isinstance(features, th.Tensor)  # one extractor shared by actor and critic
            latent = policy.mlp_extractor.forward_actor(features)
            gaussian = policy._get_action_dist_from_latent(latent).distribution  # Normal(mean, std) per action
            if not isinstance(gaussian, th.distributions.Normal):
                raise TypeError(f"clone needs a Gaussian policy, got {type(gaussian).__name__}")
            mean, std = gaussian.mean, gaussian.stddev
            action_mse = (((mean - actions[index]) ** 2).sum(dim=1) * weight).sum() / count
            held = th.distributions.Normal(mean.detach(), std)
            nll = -(held.log_prob(actions[index]).sum(dim=1) * weight).sum() / count
            actor_optimizer.zero_grad()
            (action_mse + nll).backward()
            th.nn.utils.clip_grad_norm_(policy.parameters(), 0.5)
            actor_optimizer.step()

            values = policy.value_net(policy.mlp_extractor.forward_critic(features.detach())).flatten()
            value_loss = th.nn.functional.mse_loss(values, returns[index])
            critic_optimizer.zero_grad()
            value_loss.backward()
            critic_optimizer.step()
            totals += (action_mse.item(), nll.item(), value_loss.item())
            batches += 1
        history.append(dict(zip(("action_mse", "nll", "value_loss"), totals / batches, strict=True)))
    policy.set_training_mode(False)
    return history


def track_feature_range(policy: Any, env: VecEnv, steps: int) -> None:
    """Set the feature range of a policy trained without PPO's rollouts (cloning, DAgger): the bounds h_min / h_max
    of its feature uncertainty (u_feat, the paper's eq. 7), which ODV-PPO tracks over the states its rollouts reach.
    Reset, then folded over the hidden states of at least `steps` states that `policy` reaches driving `env`
    deterministically (dropout off), from the env's current seeds."""
    policy.features_extractor.reset_feature_range()
    policy.set_training_mode(False)
    observation = env.reset()
    for _ in range(max(1, -(-int(steps) // env.num_envs))):
        with th.no_grad(), policy.feature_range_tracking():
            tensor, _ = policy.obs_to_tensor(observation)
            policy.forward(tensor, deterministic=True)  # the rollout pass, which folds h into the range
        action, _ = policy.predict(observation, deterministic=True)
        observation, _, _, _ = env.step(action)
