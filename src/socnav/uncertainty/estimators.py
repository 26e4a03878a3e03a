"""Per-step uncertainty of an ODV-PPO policy from K samples: MC-dropout or a deep ensemble (paper IV-B).
Returns the epistemic and aleatoric uncertainty per action dimension and the predictive feature uncertainty.

For an observation ``o`` the K samples ``(mu_k, sigma_k, h_k)``, k = 1..K, come from one batched forward pass:

* MC-dropout: the observation batch repeated K times (sample-major: row ``k * B + b`` is sample k of
  observation b), every dropout layer active with ``p_test``, everything else in eval mode;
* deep ensemble: K independently trained policies in eval mode (no dropout), run as one vectorised stack
  (``torch.func.stack_module_state`` + ``vmap``), or as a loop over the members where the stack cannot run.

From the samples (per action dimension: 0 = speed, 1 = heading change, as the env action)::

    mu_bar = (1/K) sum_k mu_k                                    mean action (MC / ensemble average)
    u_ep   = (1/K) sum_k (mu_k - mu_bar)^2                       epistemic, paper eq. (5)
    u_al   = (1/K) sum_k sigma_k^2                               aleatoric, paper eq. (6)
    V_d    = (1/K) sum_k (h_{d,k} - h_bar_d)^2                   feature variance per element, paper eq. (7)
    u_feat = sum_d (V_d / sum_d' V_d') * (V_d / V_max,d)         MC-dropout, paper eq. (8)
             V_max,d = (h_max,d - h_min,d)^2 / 12                the variance of U(h_min,d, h_max,d)
    u_feat = (1/D) sum_d V_d                                     ensemble, paper eq. (9)

All variances are population variances (divide by K, not K - 1), as printed in the paper. Statistics are
computed in float64 from the float32 samples.

Which action is executed
------------------------
``Uncertainty.mean_action`` is the sample average ``mu_bar``; it is *not* the action a deployed policy takes.
The deployed action is the deterministic one, ``policy.predict(obs, deterministic=True)`` (eval mode, no
dropout, clipped to the action box), which differs from ``mu_bar`` in general because dropout acts through
non-linearities. ``mu_bar`` is unclipped. The safety layer decides which one it uses.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch as th
from torch import nn

if TYPE_CHECKING:
    from socnav.rl.policy import ODVActorCriticPolicy

# The equations live in NumPy-only `stats` (shared with the torch-free runtime); re-exported here.
from socnav.uncertainty.stats import (
    Uncertainty,
    apply_feature_map,
    ensemble_feature_uncertainty,
    feature_map,
    feature_uncertainty,
    summarise_samples,
)

__all__ = [
    "ESTIMATOR_KINDS",
    "EnsembleEstimator",
    "MCDropoutEstimator",
    "Uncertainty",
    "ensemble_feature_uncertainty",
    "feature_uncertainty",
    "make_estimator",
    "obs_to_tensors",
    "repeat_obs",
    "summarise_samples",
]

ObsLike = Mapping[str, "np.ndarray | th.Tensor"]


def repeat_obs(obs: Mapping[str, th.Tensor], k: int) -> dict[str, th.Tensor]:
    """The batch repeated ``k`` times, sample-major: row ``i * B + b`` of the result is observation ``b``."""
    return {key: value.expand(k, *value.shape).reshape(-1, *value.shape[1:]) for key, value in obs.items()}


# ----------------------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------------------
def _as_policy(obj: Any) -> Any:
    """The policy of ``obj``: a policy with ``action_stats`` itself, or an SB3 model whose ``.policy`` is one."""
    if hasattr(obj, "action_stats"):
        return obj
    policy = getattr(obj, "policy", None)
    if policy is not None and hasattr(policy, "action_stats"):
        return policy
    raise TypeError(f"expected an ODVActorCriticPolicy (or a model holding one), got {type(obj).__name__}")


def obs_to_tensors(policy: Any, obs: ObsLike, repeat: int = 1) -> dict[str, th.Tensor]:
    """Observation dict (NumPy or torch, batched or single) -> batched float tensors on the policy's device,
    the batch repeated ``repeat`` times sample-major (as :func:`repeat_obs`).

    A lighter version of SB3's ``obs_to_tensor`` (which deep-copies the dict): only the keys of the
    observation space, reshaped to ``(-1, *space.shape)``; NumPy input is tiled in NumPy (cheapest).
    """
    device = policy.device
    out = {}
    for key, space in policy.observation_space.spaces.items():
        value = obs[key]
        if isinstance(value, th.Tensor):
            tensor = value.to(device=device, dtype=th.float32).reshape((-1, *space.shape))
            if repeat > 1:
                tensor = tensor.expand(repeat, *tensor.shape).reshape(-1, *space.shape)
        else:
            array = np.asarray(value, dtype=np.float32).reshape((-1, *space.shape))
            if repeat > 1:
                array = np.concatenate([array] * repeat, axis=0)
            tensor = th.from_numpy(array).to(device)
        out[key] = tensor
    return out


@contextmanager
def _eval_mode(policy: nn.Module) -> Iterator[None]:
    """Context: ``policy`` entirely in eval mode (no dropout); every module's mode is restored on exit."""
    modes = [(m, m.training) for m in policy.modules()]
    if not any(mode for _, mode in modes):  # already all in eval mode (the usual deployment state)
        yield
        return
    policy.train(False)
    try:
        yield
    finally:
        for module, mode in modes:
            module.training = mode


# ----------------------------------------------------------------------------------------------------------
# MC-dropout
# ----------------------------------------------------------------------------------------------------------
class MCDropoutEstimator:
    """MC-dropout uncertainty of one policy: K dropout samples in one batched forward pass (paper IV-B-1).

    The observation batch ``(B, ...)`` is repeated K times (sample-major, :func:`repeat_obs`) and run once
    through ``policy.action_stats`` inside ``policy.mc_dropout(p_test)``: every dropout layer (LSTM input,
    between the LSTM layers, on ``h``, after each actor hidden layer) is active with probability ``p_test``,
    every other module is in eval mode, and on exit every module's mode and every dropout ``p`` are restored
    (``mc_dropout`` records and restores them in a ``finally``; tested in ``tests/uncertainty``).

    ``h`` is the LSTM hidden state *before* the output dropout (the quantity whose range is tracked in
    training), so its spread comes from the LSTM input and between-layer dropout.

    Reproducibility: ``nn.Dropout`` draws from torch's global generator (it accepts no ``torch.Generator``).
    With ``seed`` given, every call runs inside ``torch.random.fork_rng`` on a private generator state that
    starts from ``seed`` and is carried from call to call: the sequence of masks is reproducible and the
    global RNG is left untouched. ``__call__(obs, seed=s)`` instead fixes the masks of that one call
    (``manual_seed(s)`` inside ``fork_rng``). Without either, the global RNG is used (and advanced).

    :param policy: an ``ODVActorCriticPolicy`` (or a model with one as ``.policy``).
    :param k: number of samples K (>= 2; paper: 20).
    :param p_test: MC-dropout probability; None = ``policy.p_test`` (0.5 in the presets). ``p_test = 0``
        gives K identical samples, hence ``u_ep = 0`` and ``u_feat = 0``.
    :param seed: seed of a private, reproducible dropout-mask stream (None: the global RNG).
    :param uniforms: external dropout-mask stream (a hook for comparing implementations, e.g. the ONNX runtime
        against torch): ``uniforms(layer, shape) -> array`` of U[0, 1) samples, with ``layer`` the index into
        ``policy.dropout_layers()`` and ``shape`` that layer's input shape (rows sample-major); each dropout
        layer then keeps ``uniform >= p_test``, exactly as with torch's own draws. Called in forward order, once
        per active layer and call (the LSTM-input layers are skipped when no observation of the batch has a
        human). Overrides ``seed``; see ``socnav.runtime.DropoutStream`` for a seeded NumPy stream.
    """

    kind = "mc"

    def __init__(
        self,
        policy: Any,
        k: int = 20,
        p_test: float | None = None,
        seed: int | None = None,
        uniforms: Callable[[int, tuple[int, ...]], np.ndarray] | None = None,
    ) -> None:
        self.policy = _as_policy(policy)
        if k < 2:
            raise ValueError(f"MC-dropout needs k >= 2 samples, got k={k}")
        self.k = int(k)
        self.p_test = float(self.policy.p_test if p_test is None else p_test)
        if not 0.0 <= self.p_test < 1.0:
            raise ValueError(f"p_test must lie in [0, 1), got {self.p_test}")
        if not self.policy.dropout_layers():
            raise ValueError("the policy has no dropout layers; MC-dropout needs them")
        self.seed = seed
        self.uniforms = uniforms
        self._rng_states: tuple[th.Tensor, th.Tensor | None] | None = None
        if seed is not None:
            self._rng_states = self._initial_states(int(seed))
        self._warned_range = False
        self._map_key: tuple[int, int, int, int] | None = None
        self._map: tuple[np.ndarray, np.ndarray] = (np.zeros(0, bool), np.zeros(0))

    # ---- RNG handling ------------------------------------------------------------------------------------
    def restart(self) -> None:
        """Restart the seeded mask stream from ``seed`` (no-op without a seed): runs that each start with
        ``restart()`` see the same sequence of dropout masks."""
        if self.seed is not None:
            self._rng_states = self._initial_states(int(self.seed))

    def _cuda_device(self) -> th.device | None:
        device = th.device(self.policy.device)
        return device if device.type == "cuda" else None

    def _initial_states(self, seed: int) -> tuple[th.Tensor, th.Tensor | None]:
        cuda = self._cuda_device()
        with th.random.fork_rng(devices=[cuda] if cuda is not None else []):
            th.random.default_generator.manual_seed(seed)
            if cuda is not None:
                th.cuda.manual_seed(seed)
            return th.random.get_rng_state(), (th.cuda.get_rng_state(cuda) if cuda is not None else None)

    @contextmanager
    def _private_rng(self, seed: int | None) -> Iterator[None]:
        cuda = self._cuda_device()
        with th.random.fork_rng(devices=[cuda] if cuda is not None else []):
            if seed is not None:  # per-call masks
                th.random.default_generator.manual_seed(seed)
                if cuda is not None:
                    th.cuda.manual_seed(seed)
                yield
                return
            assert self._rng_states is not None  # `samples` comes here without a seed only for a seeded stream
            cpu_state, cuda_state = self._rng_states
            th.random.set_rng_state(cpu_state)
            if cuda is not None and cuda_state is not None:
                th.cuda.set_rng_state(cuda_state, cuda)
            yield
            self._rng_states = (
                th.random.get_rng_state(),
                th.cuda.get_rng_state(cuda) if cuda is not None else None,
            )

    # ---- estimation --------------------------------------------------------------------------------------
    def samples(self, obs: ObsLike, seed: int | None = None) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """The K MC-dropout samples ``(h, mu, log_std)`` of shapes (K, B, D), (K, B, A), (K, B, A).

        Inference-mode tensors (no autograd); ``seed`` as in :meth:`__call__`.
        """
        repeated = obs_to_tensors(self.policy, obs, repeat=self.k)
        batch = repeated["robot"].shape[0] // self.k
        rng: AbstractContextManager[None] = (
            self._private_rng(seed) if seed is not None or self._rng_states is not None else nullcontext()
        )
        # inference_mode: no autograd bookkeeping at all (~5 % of the pass); the samples only go to NumPy.
        with rng, th.inference_mode(), self.policy.mc_dropout(self.p_test), self._external_uniforms():
            h, mu, log_std = self.policy.action_stats(repeated)  # one pass over K * B rows
        return h.view(self.k, batch, -1), mu.view(self.k, batch, -1), log_std.view(self.k, batch, -1)

    @contextmanager
    def _external_uniforms(self) -> Iterator[None]:
        """Context: every dropout layer draws its uniforms from ``self.uniforms`` (no-op without it)."""
        if self.uniforms is None:
            yield
            return
        layers = self.policy.dropout_layers()
        for index, layer in enumerate(layers):
            layer.uniform_source = _UniformSource(self.uniforms, index)
        try:
            yield
        finally:
            for layer in layers:
                layer.uniform_source = None

    def __call__(self, obs: ObsLike, seed: int | None = None) -> Uncertainty:
        """Uncertainty of a batch of observations (dict of (B, ...) arrays or tensors, or one observation).

        :param obs: observation dict with ``robot`` (B, 5), ``humans`` (B, M, 7), ``humans_mask`` (B, M).
        :param seed: fix the dropout masks of this call (see the class docstring).
        """
        h, mu, log_std = self.samples(obs, seed)
        mean, u_ep, u_al, feat_var = summarise_samples(mu, log_std, h)
        valid, inv_v_max = self._feature_map()
        if not self._warned_range and not valid.any():
            self._warned_range = True
            warnings.warn(
                "the policy's feature range is untracked (no rollout seen, or a model saved without one): u_feat is 0",
                RuntimeWarning,
                stacklevel=2,
            )
        return Uncertainty(mean, u_ep, u_al, apply_feature_map(feat_var, valid, inv_v_max))

    def _feature_map(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`~socnav.uncertainty.stats.feature_map` of the policy's tracked range, recomputed only when the
        range buffers changed.

        The buffers are updated in place (``update_feature_range``, ``load_state_dict``), which bumps their
        version counters; a new buffer object changes the ids.
        """
        lo, hi = self.policy.feature_range
        key = (id(lo), lo._version, id(hi), hi._version)
        if key != self._map_key:
            self._map_key, self._map = key, feature_map(lo, hi)
        return self._map


class _UniformSource:
    """``source(x)``: the uniforms of one dropout layer from an external stream, as a tensor shaped like ``x``."""

    def __init__(self, uniforms: Callable[[int, tuple[int, ...]], np.ndarray], layer: int) -> None:
        self.uniforms, self.layer = uniforms, layer

    def __call__(self, x: th.Tensor) -> th.Tensor:
        values = np.asarray(self.uniforms(self.layer, tuple(x.shape)), dtype=np.float32)
        if values.shape != tuple(x.shape):
            raise ValueError(f"uniforms for dropout layer {self.layer}: expected shape {tuple(x.shape)}, "
                             f"got {values.shape}")
        return th.from_numpy(values).to(x.device)


# ----------------------------------------------------------------------------------------------------------
# Deep ensemble
# ----------------------------------------------------------------------------------------------------------
class _ActionStats(nn.Module):
    """``forward = policy.action_stats``, so that ``torch.func.functional_call`` can run it on stacked weights."""

    policy: ODVActorCriticPolicy

    def __init__(self, policy: ODVActorCriticPolicy) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, obs: dict[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        return self.policy.action_stats(obs)


@contextmanager
def _explicit_lstm() -> Iterator[None]:
    """Context: the extractor's LSTMs run through their written-out equations for every sequence length.

    ``vmap`` has no batching rule for ``aten::lstm`` (the fused kernel that the extractor, `socnav.rl.extractor`,
    runs above ``SHORT_SEQUENCE`` humans); its written-out path gives the same values from the same weights
    and vectorises. The module constant is raised for the duration of the stacked call only; another thread
    running the extractor meanwhile would take the written-out path too (same values, different speed).
    """
    from socnav.rl import extractor

    previous = extractor.SHORT_SEQUENCE
    extractor.SHORT_SEQUENCE = 1 << 30
    try:
        yield
    finally:
        extractor.SHORT_SEQUENCE = previous


#: Policy attributes that change the forward pass without being weights (must agree to share one skeleton).
_FORWARD_SETTINGS = ("odv", "log_std_min", "log_std_max", "lstm_hidden_size", "n_lstm_layers")


class EnsembleEstimator:
    """Deep-ensemble uncertainty: K independently trained policies, dropout off (paper IV-B-2).

    Every member gets the same observation in eval mode (no dropout; members' modes are untouched by the
    stacked path and restored by the loop path). ``mean_action`` is the members' average ``mu_bar``;
    ``u_feat = (1/D) sum_d V_d`` (eq. (9)), which needs no feature range.

    Evaluation: by default the members' weights are stacked once (``torch.func.stack_module_state``) and the
    K members run as one ``vmap``-ed ``functional_call`` of ``action_stats`` on a weightless (``meta``)
    skeleton. The stack is a *snapshot*: call :meth:`refresh` after changing a member's weights. The loop
    over members (``stacked=False``, or automatically when the members cannot be stacked: different
    architectures, or a torch op without a ``vmap`` rule) gives the same numbers.

    :param policies: the K >= 2 members (``ODVActorCriticPolicy`` or models holding one), same observation
        space and feature size ``D``.
    :param stacked: True: always the stacked path (raise if impossible); False: always the loop;
        None: stacked where possible, else the loop.
    """

    kind = "ensemble"

    def __init__(self, policies: Sequence[Any], stacked: bool | None = None) -> None:
        self.policies = [_as_policy(p) for p in policies]
        if len(self.policies) < 2:
            raise ValueError(f"an ensemble needs at least 2 members, got {len(self.policies)}")
        self.k = len(self.policies)
        self._want_stacked = stacked
        self._stack: tuple[Any, dict[str, th.Tensor], dict[str, th.Tensor]] | None = None
        self.refresh()

    def refresh(self) -> None:
        """(Re-)build the stacked weights from the members' current parameters and buffers."""
        self._stack = None
        if self._want_stacked is False:
            return
        try:
            self._stack = self._build_stack()
        except (RuntimeError, ValueError, TypeError) as err:
            if self._want_stacked:
                raise ValueError(f"cannot stack the ensemble members: {err}") from err

    def _build_stack(self) -> tuple[Any, dict[str, th.Tensor], dict[str, th.Tensor]]:
        from torch.func import functional_call, stack_module_state, vmap

        wrappers = [_ActionStats(p) for p in self.policies]
        shapes = [{k: tuple(v.shape) for k, v in w.state_dict().items()} for w in wrappers]
        if any(s != shapes[0] for s in shapes[1:]):
            raise ValueError("members have different architectures")
        settings = [tuple(getattr(p, a, None) for a in _FORWARD_SETTINGS) for p in self.policies]
        if any(s != settings[0] for s in settings[1:]):  # not in the weights, but the skeleton's forward uses them
            raise ValueError(f"members differ in {', '.join(_FORWARD_SETTINGS)}")
        if len({th.device(p.device) for p in self.policies}) != 1:
            raise ValueError("members live on different devices")
        params, buffers = stack_module_state(wrappers)
        params = {k: v.detach() for k, v in params.items()}
        # Weightless skeleton (meta device) in eval mode: no dropout.
        skeleton = copy.deepcopy(_ActionStats(self.policies[0])).to("meta").train(False)

        def member(p: dict[str, th.Tensor], b: dict[str, th.Tensor], obs: dict[str, th.Tensor]):
            return functional_call(skeleton, (p, b), (obs,))

        # Weights batched over the members (dim 0), the observation shared (None).
        return vmap(member, in_dims=(0, 0, None)), params, buffers

    @property
    def stacked(self) -> bool:
        """Whether calls use the stacked (vmap) path."""
        return self._stack is not None

    def samples(self, obs: ObsLike) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """The members' ``(h, mu, log_std)`` of shapes (K, B, D), (K, B, A), (K, B, A) (inference-mode tensors)."""
        tensors = obs_to_tensors(self.policies[0], obs)
        if self._stack is not None:
            fn, params, buffers = self._stack
            try:
                with th.inference_mode(), _explicit_lstm():
                    h, mu, log_std = fn(params, buffers, tensors)
                return h, mu, log_std
            except RuntimeError:
                if self._want_stacked:
                    raise
                self._stack = None  # an op without a vmap rule: use the loop from now on
        outs = []
        for policy in self.policies:  # the loop path (see the class docstring for when it is used)
            with th.inference_mode(), _eval_mode(policy):
                outs.append(policy.action_stats(tensors))
        h, mu, log_std = (th.stack(t) for t in zip(*outs, strict=True))
        return h, mu, log_std

    def __call__(self, obs: ObsLike) -> Uncertainty:
        """Uncertainty of a batch of observations (dict of (B, ...) arrays or tensors, or one observation)."""
        h, mu, log_std = self.samples(obs)
        mean, u_ep, u_al, feat_var = summarise_samples(mu, log_std, h)
        return Uncertainty(mean, u_ep, u_al, ensemble_feature_uncertainty(feat_var))


# ----------------------------------------------------------------------------------------------------------
# Factory
# ----------------------------------------------------------------------------------------------------------
ESTIMATOR_KINDS: tuple[str, ...] = ("mc", "ensemble")


def make_estimator(
    kind: Literal["mc", "ensemble"],
    policies: Any,
    k: int = 20,
    p_test: float | None = None,
) -> MCDropoutEstimator | EnsembleEstimator:
    """Build an estimator by name.

    :param kind: ``"mc"`` (MC-dropout) or ``"ensemble"`` (deep ensemble).
    :param policies: ``"mc"``: one policy (or a sequence holding exactly one); ``"ensemble"``: the members.
    :param k: MC-dropout sample count K; ignored for ``"ensemble"`` (K = number of members).
    :param p_test: MC-dropout probability (None: the policy's ``p_test``); must be None for ``"ensemble"``.
    :raises ValueError: unknown ``kind`` (the message lists the allowed values) or inconsistent arguments.
    """
    if kind == "mc":
        if isinstance(policies, Sequence):
            if len(policies) != 1:
                raise ValueError(f"kind 'mc' takes one policy, got {len(policies)}")
            policies = policies[0]
        return MCDropoutEstimator(policies, k=k, p_test=p_test)
    if kind == "ensemble":
        if p_test is not None:
            raise ValueError("p_test applies to MC-dropout only; ensemble members run without dropout")
        if not isinstance(policies, Sequence):
            raise ValueError("kind 'ensemble' takes a sequence of policies")
        return EnsembleEstimator(policies)
    raise ValueError(f"unknown estimator kind {kind!r}; allowed values: {', '.join(map(repr, ESTIMATOR_KINDS))}")
