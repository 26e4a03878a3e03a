"""Actor-critic policy of ODV-PPO with dropout: an SB3 ``ActorCriticPolicy`` subclass (paper Fig. 3, IV-A and IV-B).
Shared LSTM features extractor, actor with dropout and observation-dependent variance (ODV), critic without dropout.

Network (``o`` an observation, ``p`` the dropout probability ``p_train``)::

    features  = [dropout(h(o)), robot(o)]                       h: 2-layer LSTM over the humans (extractor.py)
    latent_pi = dropout(tanh(W2 dropout(tanh(W1 features))))    actor MLP, 2 x 128
    latent_vf = tanh(V2 tanh(V1 features))                      critic MLP, 2 x 128, no dropout
    mu(o)        = A_mu latent_pi
    log sigma(o) = clamp(A_sigma latent_pi, -20, 0.25)          ODV ("variance clamping", paper IV-A)
    log sigma    = SB3's state-independent parameter            non-ODV variants (ppo, ppo-drop)
    value(o)     = v latent_vf
    pi(a | o)    = N(mu(o), diag sigma(o)^2)                    actions clipped to the Box by SB3, no squashing

Dropout and train/eval mode
---------------------------
Dropout is active whenever the module is in training mode, i.e. during ``ODVPPO.train()`` (SB3 calls
``policy.set_training_mode(True)``). Rollouts are collected in eval mode (SB3's default, kept on purpose): the
behaviour actions come from the same deterministic network that is deployed, the critic's GAE targets are not
perturbed through the shared extractor, and the tracked feature range describes the deterministic features.
``predict(..., deterministic=True)`` switches to eval mode, so it is dropout-free and reproducible.

MC-dropout hooks for the uncertainty estimators: :meth:`ODVActorCriticPolicy.dropout_layers`,
:meth:`ODVActorCriticPolicy.mc_dropout` and :meth:`ODVActorCriticPolicy.action_stats`.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from functools import partial
from typing import Any, TypeVar, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.distributions import Normal

from socnav.rl.extractor import Dropout, HumanLSTMExtractor

_HAS_FUSED_CPU_ADAM = tuple(int(v) for v in th.__version__.split(".")[:2]) >= (2, 4)

__all__ = [
    "DropoutMlpExtractor",
    "GaussianDistribution",
    "NonFiniteError",
    "ODVActorCriticPolicy",
    "check_finite",
]


# ----------------------------------------------------------------------------------------------------------
# NaN / Inf guard
# ----------------------------------------------------------------------------------------------------------
class NonFiniteError(FloatingPointError):
    """A loss or a policy output became NaN/Inf. ``str(err)`` names the tensor and, once known, the timestep.

    The policy raises it without a timestep (it does not know the training clock); :class:`ODVPPO` catches it
    and re-raises it with ``timestep`` filled in, e.g. ``non-finite value in 'policy.mean' at timestep 4096``.
    """

    def __init__(self, tensor_name: str, timestep: int | None = None) -> None:
        self.tensor_name = tensor_name
        self.timestep = timestep
        where = "" if timestep is None else f" at timestep {timestep}"
        super().__init__(f"non-finite value in '{tensor_name}'{where}")

    def at_timestep(self, timestep: int) -> NonFiniteError:
        """A copy of this error with the timestep filled in (kept if it was already known)."""
        return NonFiniteError(self.tensor_name, self.timestep if self.timestep is not None else timestep)


def check_finite(**tensors: th.Tensor) -> None:
    """Raise :class:`NonFiniteError` naming the first of ``tensors`` that holds a NaN or an Inf.

    One reduction per tensor and a single host synchronisation in the common (all finite) case.
    """
    flags = th.stack([th.isfinite(t).all() for t in tensors.values()])
    if bool(flags.all()):
        return
    for name, ok in zip(tensors, flags.tolist(), strict=True):
        if not ok:
            raise NonFiniteError(name)


# ----------------------------------------------------------------------------------------------------------
# Building blocks
# ----------------------------------------------------------------------------------------------------------
SelfGaussianDistribution = TypeVar("SelfGaussianDistribution", bound="GaussianDistribution")


class GaussianDistribution(DiagGaussianDistribution):
    """SB3's diagonal Gaussian, built without ``torch.distributions`` argument validation.

    Validation re-checks ``loc``/``scale``/``value`` on every call (a measurable cost on the rollout hot path)
    and would turn a NaN into an unhelpful ``ValueError``; the policy checks its outputs itself instead.
    ``log_std`` may be a per-observation tensor (B, A) (ODV) or a parameter (A,) (broadcast).
    """

    def proba_distribution(
        self: SelfGaussianDistribution, mean_actions: th.Tensor, log_std: th.Tensor
    ) -> SelfGaussianDistribution:
        self.distribution = Normal(mean_actions, log_std.exp().expand_as(mean_actions), validate_args=False)
        return self


class DropoutMlpExtractor(nn.Module):
    """Separate actor and critic MLPs on the shared features (SB3 ``MlpExtractor`` interface).

    Actor: ``[Linear -> activation -> Dropout(p)] x len(pi)``; critic: ``[Linear -> activation] x len(vf)``,
    no dropout (paper IV-B: dropout in the critic destabilises the value target).

    :param feature_dim: size of the shared features vector.
    :param pi: hidden sizes of the actor.
    :param vf: hidden sizes of the critic.
    :param activation_fn: activation class (``nn.Tanh``).
    :param dropout_p: actor dropout probability ``p_train`` (0 = identity, the module still exists).
    """

    def __init__(
        self,
        feature_dim: int,
        pi: Sequence[int],
        vf: Sequence[int],
        activation_fn: type[nn.Module] = nn.Tanh,
        dropout_p: float = 0.0,
    ) -> None:
        super().__init__()
        actor: list[nn.Module] = []
        last = feature_dim
        for size in pi:
            actor += [nn.Linear(last, size), activation_fn(), Dropout(dropout_p)]
            last = size
        self.latent_dim_pi = last
        critic: list[nn.Module] = []
        last = feature_dim
        for size in vf:
            critic += [nn.Linear(last, size), activation_fn()]
            last = size
        self.latent_dim_vf = last
        self.policy_net = nn.Sequential(*actor)
        self.value_net = nn.Sequential(*critic)

    def forward(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """``(latent_pi, latent_vf)``."""
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: th.Tensor) -> th.Tensor:
        """Actor latent (with dropout in training mode)."""
        return self.policy_net(features)

    def forward_critic(self, features: th.Tensor) -> th.Tensor:
        """Critic latent (never dropout)."""
        return self.value_net(features)

    def dropout_layers(self) -> list[nn.Dropout]:
        """The actor's dropout modules (the critic has none)."""
        return [m for m in self.policy_net if isinstance(m, nn.Dropout)]


# ----------------------------------------------------------------------------------------------------------
# The policy
# ----------------------------------------------------------------------------------------------------------
class ODVActorCriticPolicy(ActorCriticPolicy):
    """ODV-PPO actor-critic for the socnav ``Dict`` observation (``robot``, ``humans``, ``humans_mask``).

    All five paper variants are this class: ``odv`` selects the observation-dependent ``log sigma(o)`` head
    (else SB3's state-independent ``log_std`` parameter) and ``dropout_p`` the training dropout (0 = none).

    :param observation_space: socnav ``Dict`` observation space.
    :param action_space: ``Box(-1, 1, (2,))``.
    :param lr_schedule: learning-rate schedule (SB3).
    :param net_arch: ``dict(pi=[...], vf=[...])`` or a list used for both; default ``pi = vf = [128, 128]``.
    :param activation_fn: MLP activation (``nn.Tanh``).
    :param ortho_init: SB3's orthogonal initialisation (LSTM weights keep PyTorch's default init).
    :param log_std_init: initial ``log sigma`` (bias of the ODV head, value of the parameter otherwise).
    :param odv: observation-dependent variance head.
    :param dropout_p: training dropout ``p_train`` in the extractor and the actor.
    :param p_test: MC-dropout probability to use at test time (stored only; the default of :meth:`mc_dropout`).
    :param log_std_min: lower clamp of the ODV ``log sigma`` (paper: -20).
    :param log_std_max: upper clamp of the ODV ``log sigma`` (paper: 0.25).
    :param lstm_hidden_size: LSTM hidden size (64).
    :param n_lstm_layers: number of LSTM layers (2).
    :param kwargs: passed on to :class:`ActorCriticPolicy` (optimizer, ...). gSDE and a non-shared extractor are
        not supported.
    """

    features_extractor: HumanLSTMExtractor
    # SB3 declares MlpExtractor, yet lets _build_mlp_extractor install any module with its interface.
    mlp_extractor: DropoutMlpExtractor  # type: ignore[assignment]
    action_space: spaces.Box  # checked in __init__
    action_dist: GaussianDistribution
    #: The policy file's header (algo, algo_config, env_config, ...), set on policies read by `load_policy`.
    socnav_metadata: dict[str, Any]

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.Tanh,
        ortho_init: bool = True,
        log_std_init: float = 0.0,
        odv: bool = True,
        dropout_p: float = 0.0,
        p_test: float = 0.5,
        log_std_min: float = -20.0,
        log_std_max: float = 0.25,
        lstm_hidden_size: int = 64,
        n_lstm_layers: int = 2,
        features_extractor_class: type[HumanLSTMExtractor] = HumanLSTMExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        if not isinstance(action_space, spaces.Box):
            raise TypeError(f"ODVActorCriticPolicy needs a Box action space, got {action_space}")
        if kwargs.get("use_sde"):
            raise ValueError("gSDE is not supported by ODVActorCriticPolicy")
        if not kwargs.pop("share_features_extractor", True):
            raise ValueError("ODVActorCriticPolicy always shares its features extractor (paper Fig. 3)")
        if not 0.0 <= dropout_p < 1.0 or not 0.0 <= p_test < 1.0:
            raise ValueError(f"dropout probabilities must lie in [0, 1), got {dropout_p=}, {p_test=}")
        if not log_std_min < log_std_max:
            raise ValueError(f"need log_std_min < log_std_max, got {log_std_min} >= {log_std_max}")
        # Plain attributes needed by _build(), which the base constructor calls.
        self.odv = odv
        self.dropout_p = dropout_p
        self.p_test = p_test
        self.log_std_min = log_std_min
        self.log_std_max = log_std_max
        self.lstm_hidden_size = lstm_hidden_size
        self.n_lstm_layers = n_lstm_layers
        self.check_outputs = True  # NaN/Inf guard on mean, log_std, value
        self._track_feature_range = False
        optimizer_class = kwargs.get("optimizer_class", th.optim.Adam)
        if kwargs.get("optimizer_kwargs") is None and optimizer_class is th.optim.Adam:
            # SB3's eps, plus the fused (single-kernel) Adam step where torch has it on CPU (>= 2.4): the
            # per-parameter Python loop of the default Adam costs ~1 ms per gradient step on a laptop CPU.
            kwargs["optimizer_kwargs"] = dict(eps=1e-5, **({"fused": True} if _HAS_FUSED_CPU_ADAM else {}))
        fe_kwargs = dict(lstm_hidden_size=lstm_hidden_size, n_lstm_layers=n_lstm_layers, dropout_p=dropout_p)
        fe_kwargs.update(features_extractor_kwargs or {})
        if net_arch is None:
            net_arch = dict(pi=[128, 128], vf=[128, 128])
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=net_arch,
            activation_fn=activation_fn,
            ortho_init=ortho_init,
            log_std_init=log_std_init,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=fe_kwargs,
            share_features_extractor=True,
            **kwargs,
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            odv=self.odv,
            dropout_p=self.dropout_p,
            p_test=self.p_test,
            log_std_min=self.log_std_min,
            log_std_max=self.log_std_max,
            lstm_hidden_size=self.lstm_hidden_size,
            n_lstm_layers=self.n_lstm_layers,
        )
        return data

    # ---- construction ------------------------------------------------------------------------------------
    def _build_mlp_extractor(self) -> None:
        arch = self.net_arch
        pi, vf = (arch["pi"], arch["vf"]) if isinstance(arch, dict) else (arch, arch)
        self.mlp_extractor = DropoutMlpExtractor(self.features_dim, pi, vf, self.activation_fn, self.dropout_p)

    def _build(self, lr_schedule: Schedule) -> None:
        """Create heads, initialise weights (SB3 gains) and the optimizer."""
        self._build_mlp_extractor()
        action_dim = int(np.prod(self.action_space.shape))
        latent_pi = self.mlp_extractor.latent_dim_pi
        self.action_dist = GaussianDistribution(action_dim)
        self.action_net = nn.Linear(latent_pi, action_dim)  # mu(o)
        if self.odv:
            self.log_std_net = nn.Linear(latent_pi, action_dim)  # log sigma(o), ODV
        else:
            self.log_std = nn.Parameter(th.full((action_dim,), float(self.log_std_init)))  # SB3's log_std
        self.value_net = nn.Linear(self.mlp_extractor.latent_dim_vf, 1)

        if self.ortho_init:
            gains: dict[nn.Module, float] = {
                self.features_extractor: np.sqrt(2),  # only nn.Linear/Conv are touched: the LSTM keeps its init
                self.mlp_extractor: np.sqrt(2),
                self.action_net: 0.01,
                self.value_net: 1.0,
            }
            if self.odv:
                gains[self.log_std_net] = 0.01
            for module, gain in gains.items():
                module.apply(partial(self.init_weights, gain=gain))
        if self.odv:  # start at sigma ~ exp(log_std_init) everywhere, like the SB3 parameter
            nn.init.constant_(self.log_std_net.bias, float(self.log_std_init))

        # torch types the base Optimizer's constructor without `lr`, which every concrete optimizer takes.
        self.optimizer = self.optimizer_class(  # type: ignore[call-arg]
            self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)

    # ---- forward passes -----------------------------------------------------------------------------------
    def obs_to_tensor(self, observation: np.ndarray | dict[str, np.ndarray]) -> tuple[PyTorchObs, bool]:
        """SB3's conversion, given only the keys this policy was built with: a policy trained without walls acts in a
        world with walls (whose observations add ``pose`` and maybe ``scan``) on what it knows."""
        if isinstance(observation, dict) and isinstance(self.observation_space, spaces.Dict):
            observation = {key: value for key, value in observation.items() if key in self.observation_space.spaces}
        return super().obs_to_tensor(observation)

    def _features(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """``(features, h)`` for an observation dict of tensors."""
        preprocessed = preprocess_obs(obs, self.observation_space, normalize_images=self.normalize_images)
        if not isinstance(preprocessed, dict):
            raise TypeError(f"ODVActorCriticPolicy reads a Dict observation, got a {type(preprocessed).__name__}")
        return self.features_extractor.forward_with_h(preprocessed)

    def mean_log_std(self, latent_pi: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """``(mu, log sigma)``, both (B, A), from the actor latent; ODV clamps log sigma to the configured range."""
        mean = self.action_net(latent_pi)
        if self.odv:
            log_std = th.clamp(self.log_std_net(latent_pi), self.log_std_min, self.log_std_max)
        else:
            log_std = self.log_std.expand_as(mean)
        return mean, log_std

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> GaussianDistribution:
        mean, log_std = self.mean_log_std(latent_pi)
        if self.check_outputs:
            check_finite(**{"policy.mean": mean, "policy.log_std": log_std})
        return self.action_dist.proba_distribution(mean, log_std)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Rollout step: ``(actions, values, log_prob)``; one extractor pass shared by actor and critic.

        Inside :meth:`feature_range_tracking` the hidden states also update the tracked feature range.
        """
        features, h = self._features(obs)
        if self._track_feature_range:
            self.features_extractor.update_feature_range(h)
        latent_pi, latent_vf = self.mlp_extractor(features)
        values = self.value_net(latent_vf)
        if self.check_outputs:
            check_finite(**{"policy.value": values})
        distribution = self._get_action_dist_from_latent(latent_pi)
        actions = distribution.get_actions(deterministic=deterministic)
        log_prob = distribution.log_prob(actions)
        return actions.reshape((-1, *self.action_space.shape)), values, log_prob

    def evaluate_actions_and_log_std(
        self, obs: PyTorchObs, actions: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
        """Training pass: ``(values, log_prob, entropy, log_std)`` in one forward pass.

        ``log_std`` (B, A) is what the variance loss needs; ODVPPO.train uses this instead of SB3's
        ``evaluate_actions`` so that no second forward pass is needed.
        """
        features, _ = self._features(obs)
        latent_pi, latent_vf = self.mlp_extractor(features)
        values = self.value_net(latent_vf)
        mean, log_std = self.mean_log_std(latent_pi)
        if self.check_outputs:
            check_finite(**{"policy.mean": mean, "policy.log_std": log_std, "policy.value": values})
        distribution = self.action_dist.proba_distribution(mean, log_std)
        log_prob = distribution.log_prob(actions)
        entropy = distribution.entropy()
        assert entropy is not None  # SB3 types it optional; a Gaussian's entropy always exists
        return values, log_prob, entropy, log_std

    def evaluate_actions(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor | None]:
        """SB3 interface: ``(values, log_prob, entropy)``."""
        return self.evaluate_actions_and_log_std(obs, actions)[:3]

    # ---- uncertainty-estimation API ----------------------------------------------------------------------
    def action_stats(
        self, obs: dict[str, th.Tensor] | dict[str, np.ndarray]
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Per-observation ``(h, mean, log_std)`` of shapes (B, H), (B, A), (B, A), in one forward pass.

        ``h`` is the LSTM hidden state before the output dropout (the quantity whose range is tracked).
        Runs in the policy's *current* mode: call ``policy.set_training_mode(False)`` for a deterministic pass,
        or wrap in :meth:`mc_dropout` for MC-dropout samples. Gradients are not tracked. ``obs`` may be a
        dict of tensors or of NumPy arrays (batched or single). For non-ODV policies ``log_std`` is the
        state-independent parameter broadcast to (B, A).
        """
        if isinstance(next(iter(obs.values())), th.Tensor):
            tensors: PyTorchObs = cast(dict[str, th.Tensor], obs)  # a dict of tensors (its values are alike)
        else:
            tensors, _ = self.obs_to_tensor(cast(dict[str, np.ndarray], obs))
        with th.no_grad():
            features, h = self._features(tensors)
            mean, log_std = self.mean_log_std(self.mlp_extractor.forward_actor(features))
        return h, mean, log_std

    def dropout_layers(self) -> list[nn.Dropout]:
        """All dropout modules of the network: extractor (input, between LSTM layers, on h) then actor."""
        return self.features_extractor.dropout_layers() + self.mlp_extractor.dropout_layers()

    @contextmanager
    def mc_dropout(self, p: float | None = None) -> Iterator[ODVActorCriticPolicy]:
        """Context: everything in eval mode except the dropout layers, which are active with probability ``p``.

        ``p`` defaults to the stored ``p_test``. On exit every module's mode and every dropout ``p`` are
        restored. Example::

            with policy.mc_dropout(0.5):
                h, mu, log_std = policy.action_stats(obs_repeated_k_times)
        """
        p = self.p_test if p is None else float(p)
        if not 0.0 <= p < 1.0:
            raise ValueError(f"MC-dropout probability must lie in [0, 1), got {p}")
        modules = list(self.modules())
        modes = [m.training for m in modules]
        layers = self.dropout_layers()
        old_p = [d.p for d in layers]
        # object.__setattr__: nn.Module.__setattr__ / train() cost ~4 us per module, a fifth of an MC estimate.
        for m in modules:
            object.__setattr__(m, "training", False)
        for d in layers:
            d.p = p
            object.__setattr__(d, "training", True)
        try:
            yield self
        finally:
            for d, q in zip(layers, old_p, strict=True):
                d.p = q
            for m, mode in zip(modules, modes, strict=True):
                object.__setattr__(m, "training", mode)

    @contextmanager
    def feature_range_tracking(self) -> Iterator[None]:
        """Context in which :meth:`forward` (the rollout pass) folds ``h`` into the tracked feature range."""
        previous, self._track_feature_range = self._track_feature_range, True
        try:
            yield
        finally:
            self._track_feature_range = previous

    @property
    def feature_range(self) -> tuple[th.Tensor, th.Tensor]:
        """Tracked ``(h_min, h_max)``, each (H,); +inf / -inf where nothing was observed yet."""
        return self.features_extractor.h_min, self.features_extractor.h_max
