"""ODV-PPO: Stable-Baselines3 PPO plus the paper's variance loss, a NaN/Inf guard and feature-range tracking.
Paper section IV-A, eq. (4).

Total loss minimised per minibatch: the paper's policy loss ``L_CLIP + L_sigma`` (section IV-A) with PPO's value and
entropy terms (Schulman et al. 2017, eq. 9, as in SB3)::

    L = L_CLIP + L_sigma + c_v * L_value - c_ent * H

    L_sigma = (t / T) * lambda_sigma * (1/B) * sum_b 1/2 * || sigma^2(o_b) - sigma^2_tgt ||^2      (paper eq. 4)

with ``t`` the current timestep (``num_timesteps`` when the update starts), ``T`` the total timesteps of the run
(SB3's ``_total_timesteps``; resuming with ``learn(remaining, reset_num_timesteps=False)`` keeps ``T`` the
original total), ``lambda_sigma = 0.3`` and ``sigma^2_tgt = 0``.

Why ``train()`` is re-implemented: SB3's ``PPO.train`` builds the loss and calls ``backward()`` inside one loop
with no hook for an extra term, so the only faithful way to add ``L_sigma`` to the *same* gradient step is to
write that loop out again. It is written below in the same order as SB3's (advantage normalisation, clipped
surrogate, optional value clipping, entropy, approx-KL early stop, grad-norm clipping, same log keys), plus
the variance term, the guard and the extra logs. ``log sigma`` comes out of the same forward pass as the log
probabilities (``policy.evaluate_actions_and_log_std``), so the variance loss costs no extra pass.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any, ClassVar, NamedTuple

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import HumanOutputFormat, Logger
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import MaybeCallback, RolloutBufferSamples
from stable_baselines3.common.utils import explained_variance
from stable_baselines3.common.vec_env import VecEnv
from torch.nn import functional as F

from socnav.rl.policy import NonFiniteError, ODVActorCriticPolicy, check_finite

__all__ = ["ODVPPO", "variance_loss"]


def variance_loss(
    log_std: th.Tensor,
    target_variance: float | Sequence[float] | th.Tensor = 0.0,
    coef: float = 1.0,
) -> th.Tensor:
    """Paper eq. (4) without the schedule folded in: ``coef * (1/B) sum_b 1/2 ||sigma_b^2 - sigma_tgt^2||^2``.

    :param log_std: (B, A) log standard deviations ``log sigma(o_b)``.
    :param target_variance: ``sigma^2_tgt``, a scalar or one value per action dimension.
    :param coef: multiplier, ``(t / T) * lambda_sigma`` in ODV-PPO.
    :return: scalar tensor (differentiable w.r.t. ``log_std``).
    """
    variance = th.exp(2.0 * log_std)  # sigma^2 (B, A)
    target = th.as_tensor(target_variance, dtype=variance.dtype, device=variance.device)
    per_sample = 0.5 * ((variance - target) ** 2).sum(dim=-1)  # 1/2 ||sigma^2(o_b) - sigma^2_tgt||^2
    return coef * per_sample.mean()  # (1/B) sum_b


# PPO seeks the optimal policy, paper eq. (3): the largest expected return, eq. (2), over trajectories as eq. (1).
class ODVPPO(PPO):
    """PPO with observation-dependent variance (ODV) and the variance loss of paper eq. (4).

    Identical to SB3's :class:`~stable_baselines3.PPO` (all its arguments are accepted) except:

    * the loss gets ``L_sigma`` (``variance_coef = lambda_sigma``, ``variance_target = sigma^2_tgt``), logged as
      ``train/variance_loss`` (together with ``train/variance_schedule`` = t/T and ``train/std`` = mean sigma)
      whenever the policy is ODV or ``variance_coef > 0``;
    * a NaN/Inf in any loss term, in the gradient norm or in the policy outputs (mean, log_std, value, during
      rollouts and updates) raises :class:`NonFiniteError`, e.g. ``non-finite value in 'variance_loss' at
      timestep 4096``;
    * during rollout collection the policy tracks the running min/max of its LSTM features (saved buffers).

    The default policy is :class:`ODVActorCriticPolicy`; build the paper's presets with
    :func:`socnav.rl.presets.make_model`.

    :param policy: policy class or alias (``"ODVPolicy"``).
    :param env: the training environment (SB3 ``VecEnv`` or a Gymnasium env).
    :param variance_coef: ``lambda_sigma`` (0.3 in the paper; 0 disables the term).
    :param variance_target: ``sigma^2_tgt``, scalar or per action dimension (0 in the paper).
    :param kwargs: any :class:`~stable_baselines3.PPO` argument.
    """

    #: the preset that built the model (`socnav.rl.presets.make_model`) and its hyperparameters, saved with it
    algo_name: str
    algo_config: dict[str, Any]
    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **PPO.policy_aliases,
        "ODVPolicy": ODVActorCriticPolicy,
    }
    policy: ODVActorCriticPolicy

    def __init__(
        self,
        policy: str | type[ODVActorCriticPolicy] = ODVActorCriticPolicy,
        env: Any = None,
        variance_coef: float = 0.3,
        variance_target: float | Sequence[float] = 0.0,
        **kwargs: Any,
    ) -> None:
        self.variance_coef = float(variance_coef)
        target = np.asarray(variance_target, dtype=np.float64)
        self.variance_target: float | list[float] = float(target) if target.ndim == 0 else [float(v) for v in target]
        super().__init__(policy, env, **kwargs)  # type: ignore[arg-type]

    # ---- schedule ----------------------------------------------------------------------------------------
    def variance_schedule(self) -> float:
        """``t / T`` of paper eq. (4): current over total timesteps of the run, clipped to [0, 1]."""
        total = max(int(self._total_timesteps), 1)
        return float(np.clip(self.num_timesteps / total, 0.0, 1.0))

    def _logs_variance(self) -> bool:
        return bool(getattr(self.policy, "odv", False)) or self.variance_coef > 0.0

    # ---- rollouts: track feature range, name the timestep on NaN ---------------------------------------------
    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """SB3's rollout collection (eval mode, no dropout) with feature-range tracking and the NaN guard."""
        try:
            with self.policy.feature_range_tracking():
                return super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)
        except NonFiniteError as err:
            raise err.at_timestep(self.num_timesteps) from None

    def _setup_learn(self, total_timesteps: int, callback: MaybeCallback = None, reset_num_timesteps: bool = True,
                     tb_log_name: str = "run", progress_bar: bool = False) -> tuple[int, BaseCallback]:
        """SB3's set-up, except that without TensorBoard the logger gets no folder: SB3's would create an empty
        ``SB3-<time>`` folder in the temp directory at every ``learn`` (hundreds for one table)."""
        if self._custom_logger or self.tensorboard_log is not None:
            return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        self._logger = Logger(folder=None, output_formats=[HumanOutputFormat(sys.stdout)] if self.verbose >= 1 else [])
        self._custom_logger = True  # for this set-up only: SB3 would replace the logger
        try:
            return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        finally:
            self._custom_logger = False

    def learn(  # type: ignore[override]
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "ODVPPO",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> ODVPPO:
        """SB3's ``PPO.learn``; afterwards the policy is left in eval mode (dropout off), ready for inference.

        ``total_timesteps`` is ``T`` of the variance-loss schedule; with ``reset_num_timesteps=False`` SB3 adds
        the timesteps already done, so resuming with the *remaining* steps keeps the original ``T``.
        """
        try:
            return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps,
                                 progress_bar)
        finally:
            self.policy.set_training_mode(False)

    # ---- update ----------------------------------------------------------------------------------------------
    def train(self) -> None:
        """One PPO update over the rollout buffer (``n_epochs`` passes of minibatches), with ``L_sigma`` added."""
        try:
            self._train_epochs()
        except NonFiniteError as err:
            raise err.at_timestep(self.num_timesteps) from None

    def _train_epochs(self) -> None:
        """SB3's ``PPO.train`` loop (same steps, same order) with ``L_sigma`` in each minibatch's loss: ``n_epochs``
        passes over the rollout buffer in minibatches, stopped early when the approximate KL exceeds
        ``1.5 * target_kl``."""
        policy = self.policy
        policy.set_training_mode(True)  # dropout ON (p_train) for the gradient steps
        self._update_learning_rate(policy.optimizer)
        clip_range = float(self.clip_range(self._current_progress_remaining))  # type: ignore[operator]
        clip_range_vf = None
        if self.clip_range_vf is not None:
            clip_range_vf = float(self.clip_range_vf(self._current_progress_remaining))  # type: ignore[operator]
        schedule = self.variance_schedule()  # t / T
        sigma_coef = schedule * self.variance_coef  # (t / T) * lambda_sigma

        logs: dict[str, list[th.Tensor]] = {k: [] for k in ("pg", "value", "entropy", "variance", "clip", "std")}
        approx_kl_divs: list[th.Tensor] = []
        loss = th.zeros(())
        continue_training = True
        for epoch in range(self.n_epochs):
            approx_kl_divs = []  # the logged approx_kl is the last epoch's
            for batch in self.rollout_buffer.get(self.batch_size):
                losses = self._minibatch_losses(batch, clip_range, clip_range_vf, sigma_coef)
                loss = losses.total
                approx_kl = _log_minibatch(losses, clip_range, logs, approx_kl_divs)
                if self.target_kl is not None and float(approx_kl) > 1.5 * self.target_kl:
                    continue_training = False
                    if self.verbose >= 1:
                        print(f"Early stopping at step {epoch} due to reaching max kl: {float(approx_kl):.2f}")
                    break
                self._gradient_step(loss)

            self._n_updates += 1
            if not continue_training:
                break
        self._record_update(logs, approx_kl_divs, loss, schedule, clip_range, clip_range_vf)

    def _minibatch_losses(self, batch: RolloutBufferSamples, clip_range: float, clip_range_vf: float | None,
                          sigma_coef: float) -> _MinibatchLosses:
        """The loss terms of one minibatch, from one forward pass of the policy (in training mode)."""
        values, log_prob, entropy, log_std = self.policy.evaluate_actions_and_log_std(
            batch.observations, batch.actions
        )
        values = values.flatten()

        advantages = batch.advantages
        if self.normalize_advantage and len(advantages) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

        # L_CLIP = -E[min(r A, clip(r, 1-eps, 1+eps) A)],  r = pi(a|o) / pi_old(a|o)
        log_ratio = log_prob - batch.old_log_prob
        ratio = th.exp(log_ratio)
        pg_loss = -th.min(advantages * ratio,
                          advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)).mean()

        # L_value = E[(R - V(o))^2], optionally with V clipped around the rollout value
        if clip_range_vf is None:
            values_pred = values
        else:
            values_pred = batch.old_values + th.clamp(values - batch.old_values, -clip_range_vf, clip_range_vf)
        value_loss = F.mse_loss(batch.returns, values_pred)

        # -H: entropy bonus (Gaussian entropy is analytic)
        entropy_loss = -th.mean(entropy)

        # L_sigma = (t/T) * lambda_sigma * (1/B) sum_b 1/2 ||sigma^2(o_b) - sigma^2_tgt||^2   (eq. 4)
        sigma_loss = variance_loss(log_std, self.variance_target, coef=sigma_coef)

        # L = L_CLIP + L_sigma + c_v L_value - c_ent H
        loss = pg_loss + sigma_loss + self.vf_coef * value_loss + self.ent_coef * entropy_loss
        check_finite(
            policy_gradient_loss=pg_loss,
            value_loss=value_loss,
            entropy_loss=entropy_loss,
            variance_loss=sigma_loss,
            loss=loss,
        )
        return _MinibatchLosses(pg_loss, value_loss, entropy_loss, sigma_loss, loss, ratio, log_ratio, log_std)

    def _gradient_step(self, loss: th.Tensor) -> None:
        """One optimiser step on ``loss``, the gradient norm clipped to ``max_grad_norm`` (and checked finite)."""
        policy = self.policy
        policy.optimizer.zero_grad()
        loss.backward()
        grad_norm = th.nn.utils.clip_grad_norm_(policy.parameters(), self.max_grad_norm)
        check_finite(grad_norm=grad_norm)
        policy.optimizer.step()

    def _record_update(self, logs: dict[str, list[th.Tensor]], approx_kl_divs: list[th.Tensor], loss: th.Tensor,
                       schedule: float, clip_range: float, clip_range_vf: float | None) -> None:
        """SB3's ``train/...`` values of the update (means over its minibatches), plus ``std`` and, for ODV or a
        variance loss, ``variance_loss`` and ``variance_schedule``."""
        buffer = self.rollout_buffer
        explained_var = explained_variance(buffer.values.flatten(), buffer.returns.flatten())
        record = self.logger.record
        record("train/entropy_loss", _mean(logs["entropy"]))
        record("train/policy_gradient_loss", _mean(logs["pg"]))
        record("train/value_loss", _mean(logs["value"]))
        record("train/approx_kl", _mean(approx_kl_divs))
        record("train/clip_fraction", _mean(logs["clip"]))
        record("train/loss", loss.item())
        record("train/explained_variance", float(explained_var))
        record("train/std", _mean(logs["std"]))
        if self._logs_variance():
            record("train/variance_loss", _mean(logs["variance"]))
            record("train/variance_schedule", schedule)
        record("train/n_updates", self._n_updates, exclude="tensorboard")
        record("train/clip_range", clip_range)
        if clip_range_vf is not None:
            record("train/clip_range_vf", clip_range_vf)


class _MinibatchLosses(NamedTuple):
    """The loss terms of one minibatch (``total`` = ``L``), and the tensors the logs are computed from."""

    policy_gradient: th.Tensor
    value: th.Tensor
    entropy: th.Tensor
    variance: th.Tensor
    total: th.Tensor
    ratio: th.Tensor
    log_ratio: th.Tensor
    log_std: th.Tensor


def _log_minibatch(losses: _MinibatchLosses, clip_range: float, logs: dict[str, list[th.Tensor]],
                   approx_kl_divs: list[th.Tensor]) -> th.Tensor:
    """Append the minibatch's log values to `logs` and its approximate KL to `approx_kl_divs`; returns that KL."""
    with th.no_grad():  # http://joschu.net/blog/kl-approx.html, as in SB3
        approx_kl = th.mean((losses.ratio - 1) - losses.log_ratio)
        # kept as tensors and reduced once per update: a host round trip per value and step adds up
        approx_kl_divs.append(approx_kl)
        logs["pg"].append(losses.policy_gradient.detach())
        logs["value"].append(losses.value.detach())
        logs["entropy"].append(losses.entropy.detach())
        logs["variance"].append(losses.variance.detach())
        logs["clip"].append(th.mean((th.abs(losses.ratio - 1) > clip_range).float()))
        logs["std"].append(losses.log_std.detach().exp().mean())
    return approx_kl


def _mean(values: list[th.Tensor]) -> float:
    """The mean of scalar tensors as a float (NaN for none)."""
    return float(th.stack(values).mean()) if values else float("nan")
