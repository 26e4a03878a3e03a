"""LSTM features extractor of the ODV-PPO network (paper Fig. 3, SPEC section 3).
Encodes the variable-length list of humans with a 2-layer LSTM (closest human last) and appends the robot state.

Shapes used below: ``B`` batch, ``M`` max_humans (padded rows), ``L = max_b n_b`` real rows in the batch,
``F = 7`` features per human, ``H`` LSTM hidden size, ``R = 5`` robot features.

The trimmed-LSTM trick
----------------------
The real humans of a sample are a *prefix* of the ``humans`` rows (``humans_mask`` is ``1`` on rows
``0 .. n_b-1``). An LSTM is causal, so its top-layer output at step ``n_b - 1`` depends only on rows
``0 .. n_b - 1``: running the LSTM over the first ``L = max(n)`` rows of the whole batch and *gathering* the
output at step ``n_b - 1`` for every sample gives exactly the final hidden state that
``pack_padded_sequence`` would give, without the packing overhead (tested in ``tests/rl/test_policy.py``).
Samples with ``n_b = 0`` get the zero hidden state (the LSTM's initial state).
"""

from __future__ import annotations

from collections.abc import Callable

import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

__all__ = ["Dropout", "HumanLSTMExtractor"]

class Dropout(nn.Dropout):
    """`nn.Dropout` with the mask drawn as ``uniform >= p``: the same distribution, ~25 % cheaper on CPU.

    torch's CPU dropout draws its mask with `bernoulli_`, which is markedly slower than the vectorised uniform
    generator at these sizes; a subclass keeps `isinstance(m, nn.Dropout)` true for MC-dropout and for users.
    ``uniform_source`` (None: torch's RNG) is the hook through which ``MCDropoutEstimator(uniforms=...)`` feeds
    externally drawn uniforms, so that another implementation (the ONNX runtime) can see the same masks.
    """

    uniform_source: Callable[[th.Tensor], th.Tensor] | None = None

    def forward(self, x: th.Tensor) -> th.Tensor:
        if not self.training or self.p == 0.0:
            return x
        uniform = th.rand_like(x) if self.uniform_source is None else self.uniform_source(x)
        keep = (uniform >= self.p).to(x.dtype)
        return x * keep * (1.0 / (1.0 - self.p))


#: Sequences up to this length run through the explicit LSTM equations below instead of `nn.LSTM`'s kernel.
SHORT_SEQUENCE = 5


def _run_lstm(lstm: nn.LSTM, x: th.Tensor) -> th.Tensor:
    """Outputs (B, L, H) of a single-layer, batch-first `lstm` from the zero state, the same values as `lstm(x)[0]`.

    For the few humans of most scenes the oneDNN LSTM kernel costs more in per-call overhead than in arithmetic
    (forward + backward, B = 128, one thread: L = 1 ~1.8 ms vs ~1.0 ms written out; L = 5 ~7.4 vs ~6.6 ms; L = 10 ~9.6 vs ~15 ms), and PPO makes thousands of
    such small gradient steps. Longer sequences use the kernel. Same parameters either way:
        i, f, g, o = split(W_ih x_t + b_ih + W_hh h_{t-1} + b_hh)
        c_t = sigmoid(f) * c_{t-1} + sigmoid(i) * tanh(g),   h_t = sigmoid(o) * tanh(c_t),   h_0 = c_0 = 0
    """
    steps = x.shape[1]
    if steps > SHORT_SEQUENCE:
        return lstm(x)[0]
    input_gates = nn.functional.linear(x, lstm.weight_ih_l0, lstm.bias_ih_l0 + lstm.bias_hh_l0)  # (B, L, 4H)
    outputs = []
    hidden = cell = None
    for t in range(steps):
        gates = input_gates[:, t]
        if hidden is not None:  # W_hh h_{t-1} vanishes at t = 0
            gates = gates + nn.functional.linear(hidden, lstm.weight_hh_l0)
        input_gate, forget_gate, candidate, output_gate = gates.chunk(4, dim=1)
        new_cell = th.sigmoid(input_gate) * th.tanh(candidate)
        cell = new_cell if cell is None else th.sigmoid(forget_gate) * cell + new_cell
        hidden = th.sigmoid(output_gate) * th.tanh(cell)
        outputs.append(hidden)
    return th.stack(outputs, dim=1)


class HumanLSTMExtractor(BaseFeaturesExtractor):
    """Shared features extractor: ``features = [dropout(h), robot]`` with ``h`` the LSTM's final hidden state.

    Dropout (probability ``dropout_p``, the paper's ``p_train``) sits on the LSTM input, between the LSTM
    layers and on ``h``; it is an ordinary :class:`torch.nn.Dropout` module in each place, so an MC-dropout
    estimator can find and re-parameterise it (see :meth:`dropout_layers`). With ``dropout_p = 0`` the
    modules still exist but are the identity.

    The running per-element minimum / maximum of ``h`` (the LSTM part only, *before* the output dropout; the
    robot part is the raw observation and carries no model uncertainty) are kept in the registered buffers
    ``h_min`` / ``h_max`` and therefore saved with the model. They are updated by :meth:`update_feature_range`,
    which the policy calls on rollout observations during training.

    :param observation_space: ``Dict(robot=Box(5,), humans=Box(M, 7), humans_mask=Box(M,))``.
    :param lstm_hidden_size: hidden size ``H`` of each LSTM layer (default 64).
    :param n_lstm_layers: number of stacked LSTM layers (default 2).
    :param dropout_p: dropout probability during training (``p_train``), 0 disables dropout.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        lstm_hidden_size: int = 64,
        n_lstm_layers: int = 2,
        dropout_p: float = 0.0,
    ) -> None:
        robot_dim = int(observation_space["robot"].shape[0])
        human_dim = int(observation_space["humans"].shape[-1])
        super().__init__(observation_space, features_dim=lstm_hidden_size + robot_dim)
        if n_lstm_layers < 1:
            raise ValueError(f"n_lstm_layers must be >= 1, got {n_lstm_layers}")
        self.lstm_hidden_size = lstm_hidden_size
        self.robot_dim = robot_dim
        # One single-layer nn.LSTM per layer (instead of nn.LSTM(num_layers=2, dropout=p)) so that the
        # between-layer dropout is a visible nn.Dropout module, not a flag hidden inside the LSTM kernel.
        self.lstm_layers = nn.ModuleList(
            nn.LSTM(human_dim if i == 0 else lstm_hidden_size, lstm_hidden_size, batch_first=True)
            for i in range(n_lstm_layers)
        )
        # input_dropout before layer 0, then one dropout in front of every further layer.
        self.input_dropouts = nn.ModuleList(Dropout(dropout_p) for _ in range(n_lstm_layers))
        self.h_dropout = Dropout(dropout_p)
        # Feature range of h, tracked from rollout observations (+inf / -inf = nothing seen yet).
        self.register_buffer("h_min", th.full((lstm_hidden_size,), float("inf")))
        self.register_buffer("h_max", th.full((lstm_hidden_size,), float("-inf")))

    # ------------------------------------------------------------------------------------------------------
    def encode_humans(self, humans: th.Tensor, mask: th.Tensor) -> th.Tensor:
        """Final top-layer hidden state ``h`` (B, H) of the LSTM over the real human rows (closest last).

        :param humans: (B, M, F) human rows, real rows first (a prefix), zero padding after.
        :param mask: (B, M) 1.0 for real rows.
        """
        batch = humans.shape[0]
        n = mask.sum(dim=1).round().long()  # (B,) number of real humans n_b
        max_n = int(n.max()) if batch > 0 else 0
        if max_n == 0:  # nobody around anywhere in the batch: h = initial LSTM state = 0
            return humans.new_zeros(batch, self.lstm_hidden_size)

        x = humans[:, :max_n]  # (B, L, F): trimmed to the longest real sequence in the batch
        for dropout, lstm in zip(self.input_dropouts, self.lstm_layers):
            x = _run_lstm(lstm, dropout(x))  # (B, L, H)
        # h_b = x[b, n_b - 1]; rows after n_b - 1 were computed from padding but are never read.
        last = (n - 1).clamp(min=0)
        h = x[th.arange(batch, device=x.device), last]  # (B, H)
        return h * (n > 0).unsqueeze(1).to(h.dtype)  # n_b = 0  =>  h_b = 0

    def forward_with_h(self, observations: dict[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
        """Return ``(features, h)``: the features for the heads and the (pre-dropout) LSTM hidden state."""
        h = self.encode_humans(observations["humans"], observations["humans_mask"])
        features = th.cat([self.h_dropout(h), observations["robot"]], dim=1)  # (B, H + R)
        return features, h

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:  # type: ignore[override]
        """SB3 entry point: the features vector ``[dropout(h), robot]`` of shape (B, H + R)."""
        return self.forward_with_h(observations)[0]

    # ------------------------------------------------------------------------------------------------------
    @th.no_grad()
    def update_feature_range(self, h: th.Tensor) -> None:
        """Fold a batch of hidden states ``h`` (B, H) into the running element-wise min / max buffers."""
        if h.numel() == 0:
            return
        th.minimum(self.h_min, h.min(dim=0).values, out=self.h_min)
        th.maximum(self.h_max, h.max(dim=0).values, out=self.h_max)

    def reset_feature_range(self) -> None:
        """Forget the tracked feature range (back to +inf / -inf)."""
        self.h_min.fill_(float("inf"))
        self.h_max.fill_(float("-inf"))

    def dropout_layers(self) -> list[nn.Dropout]:
        """The extractor's dropout modules, input side first."""
        return [*self.input_dropouts, self.h_dropout]
