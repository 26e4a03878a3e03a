"""LSTM features extractor of the ODV-PPO network (paper Fig. 3 and IV-B; docs/training.md).
Encodes the variable-length list of humans with a 2-layer LSTM (closest human last) and appends the robot state.

Shapes used below: ``B`` batch, ``M`` max_humans (padded rows), ``L = max_b n_b`` real rows in the batch,
``F = 7`` features per human, ``H`` LSTM hidden size, ``R = 5`` robot features, ``S`` scan features.

With a range scan in the observation (``scan``, a world with walls: `socnav.sim.walls`) a small 1-D convolution
over the beams (:class:`ScanEncoder`) adds ``S`` features after the robot's; the robot's ``pose`` in the map frame
is never an input (absolute map coordinates would tie the policy to the one map it was trained on).

The observation gives the humans in the goal frame (the paper's) and the scan in the robot's heading frame (as a
``LaserScan``). With ``frame="heading"`` the extractor first rotates the humans' positions and velocities into the
heading frame (:func:`to_heading_frame`) and appends the goal's direction in it, so that every input the network
reads shares one robot-centric frame. It is a fixed rotation by the observation's own relative heading, so the
environment, its controllers and the safety triggers (all of which read the goal frame) are untouched, and the
exported graph carries the rotation.

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
from typing import cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from socnav.sim.walls import SCAN_KEY

__all__ = ["FRAMES", "SCAN_ENCODINGS", "Dropout", "HumanLSTMExtractor", "ScanEncoder", "to_heading_frame"]

#: What the scan encoder reads of each beam (`AlgoConfig.scan_encoding`, :meth:`ScanEncoder.normalise`).
SCAN_ENCODINGS = ("range", "nearness")
#: The frames the extractor can read the humans and the goal in (`AlgoConfig.frame`).
FRAMES = ("goal", "heading")
#: Columns of a human row that are 2-D vectors (relative position, relative velocity) and of the robot row the
#: heading relative to the goal direction (socnav.envs.spaces).
_HUMAN_VECTORS = ((0, 1), (2, 3))
_RELATIVE_HEADING = 1


def to_heading_frame(robot: th.Tensor, humans: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """The robot row extended by the goal direction, and the human rows, in the robot's heading frame.

    The robot row holds ``theta = heading - goal direction``; a vector ``(x, y)`` of the goal frame is
    ``(cos(theta) x + sin(theta) y, -sin(theta) x + cos(theta) y)`` in the heading frame, and the goal lies at angle
    ``-theta``: the robot row gains ``(cos(theta), -sin(theta))``. Zero padding rows stay zero.

    :param robot: (B, R) robot rows; :param humans: (B, M, F) human rows (goal frame).
    :return: ``(robot (B, R + 2), humans (B, M, F))``.
    """
    theta = robot[:, _RELATIVE_HEADING]
    cos, sin = th.cos(theta).unsqueeze(1), th.sin(theta).unsqueeze(1)  # (B, 1): broadcast over the rows
    columns = list(humans.unbind(dim=2))
    for x_col, y_col in _HUMAN_VECTORS:
        x, y = columns[x_col], columns[y_col]
        columns[x_col], columns[y_col] = cos * x + sin * y, cos * y - sin * x
    goal_direction = th.stack((th.cos(theta), -th.sin(theta)), dim=1)
    return th.cat((robot, goal_direction), dim=1), th.stack(columns, dim=2)

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
    (forward + backward, B = 128, one thread: L = 1 ~1.8 ms vs ~1.0 ms written out; L = 5 ~7.4 vs ~6.6 ms;
    L = 10 ~9.6 vs ~15 ms), and PPO makes thousands of such small gradient steps. Longer sequences use the kernel.
    Same parameters either way:
        i, f, g, o = split(W_ih x_t + b_ih + W_hh h_{t-1} + b_hh)
        c_t = sigmoid(f) * c_{t-1} + sigmoid(i) * tanh(g),   h_t = sigmoid(o) * tanh(c_t),   h_0 = c_0 = 0
    """
    steps = x.shape[1]
    if steps > SHORT_SEQUENCE:
        return lstm(x)[0]
    # nn.LSTM registers its parameters by name at run time, so torch's stubs type them Tensor | Module.
    weight_ih, weight_hh = cast(th.Tensor, lstm.weight_ih_l0), cast(th.Tensor, lstm.weight_hh_l0)
    bias_ih, bias_hh = cast(th.Tensor, lstm.bias_ih_l0), cast(th.Tensor, lstm.bias_hh_l0)
    input_gates = nn.functional.linear(x, weight_ih, bias_ih + bias_hh)  # (B, L, 4H)
    outputs = []
    hidden: th.Tensor | None = None
    cell: th.Tensor | None = None
    for t in range(steps):
        gates = input_gates[:, t]
        if hidden is not None:  # W_hh h_{t-1} vanishes at t = 0
            gates = gates + nn.functional.linear(hidden, weight_hh)
        input_gate, forget_gate, candidate, output_gate = gates.chunk(4, dim=1)
        new_cell = th.sigmoid(input_gate) * th.tanh(candidate)
        cell = new_cell if cell is None else th.sigmoid(forget_gate) * cell + new_cell
        hidden = th.sigmoid(output_gate) * th.tanh(cell)
        outputs.append(hidden)
    return th.stack(outputs, dim=1)


class BeamPadding(nn.Module):
    """Pads the beam axis of (B, C, N) by ``width`` on each side: wrapped around for a full-circle scan (its first
    and last beams are neighbours), zeros otherwise (beyond the field of view there is nothing)."""

    wrapped: th.Tensor  # (N + 2 width,) source beam of each padded position; a buffer, circular padding only

    def __init__(self, beams: int, width: int, circular: bool) -> None:
        super().__init__()
        self.width, self.circular = width, circular
        if circular:  # beam (i - width) mod N at padded position i: right for any N, even one under the padding
            wrapped = th.tensor([(i - width) % beams for i in range(beams + 2 * width)], dtype=th.long)
            self.register_buffer("wrapped", wrapped, persistent=False)

    def forward(self, x: th.Tensor) -> th.Tensor:
        if self.circular:
            return x.index_select(2, self.wrapped)
        return nn.functional.pad(x, (self.width, self.width))


class ScanEncoder(nn.Module):
    """The range scan as ``S`` features: two strided 1-D convolutions over the beams and a linear layer.

    ``x = scan / max_range`` (``encoding="range"``) or ``x = exp(-scan / NEARNESS_SCALE)`` (``"nearness"``), both
    in [0, 1] (:meth:`normalise`); then, with ``Dropout`` in front of every layer that has weights and on the
    output (the places the LSTM path has them, so that MC-dropout samples this branch too)::

        c1 = relu(conv(dropout(x)))        1 -> 8 channels, kernel 5, stride 2:   N -> ceil(N / 2) beams
        c2 = relu(conv(dropout(c1)))       8 -> 16 channels, kernel 5, stride 2:  -> ceil(N / 4) beams
        s  = dropout(tanh(W dropout(c2)))  S features, bounded as the LSTM state h is

    Each convolution sees its input padded by 2 beams on both sides: wrapped around (:class:`BeamPadding`) for a
    360-degree scan, zeros for a narrower field of view. Every dropout acts on a flat (B, width) tensor, the shape
    the exported navigator's keep masks have (`socnav.export`). ``layers`` is one ``nn.Sequential``: the exporter
    walks it and puts its keep masks where the dropout modules are. The policy's orthogonal initialisation (SB3's
    ``init_weights``: ``nn.Linear`` and ``nn.Conv2d`` only) re-draws the linear layer; the convolutions keep
    PyTorch's default initialisation.

    :param beams: N, the scan's beams. :param max_range: the range a beam reads when it hits nothing (m).
    :param fov: field of view in degrees (360: circular padding). :param dropout_p: the dropout probability.
    :param features: S. :param channels: channels of the two convolutions.
    :param encoding: ``"range"`` or ``"nearness"`` (:data:`SCAN_ENCODINGS`).
    """

    KERNEL, STRIDE = 5, 2
    #: The length (m) over which a beam's nearness falls by e: 1 at contact, 0.37 at 1 m, 0.0003 at 8 m.
    NEARNESS_SCALE = 1.0

    def __init__(self, beams: int, max_range: float, fov: float, dropout_p: float, features: int = 32,
                 channels: tuple[int, int] = (8, 16), encoding: str = "range") -> None:
        super().__init__()
        if not (beams >= 1 and np.isfinite(max_range) and max_range > 0.0):
            raise ValueError(f"a scan needs beams >= 1 and a finite max_range > 0, got {beams} and {max_range}")
        if encoding not in SCAN_ENCODINGS:
            raise ValueError(f"scan_encoding must be one of {list(SCAN_ENCODINGS)}, got {encoding!r}")
        self.beams, self.max_range, self.fov, self.features = int(beams), float(max_range), float(fov), int(features)
        self.encoding = encoding
        circular = self.fov >= 360.0
        pad = self.KERNEL // 2
        layers: list[nn.Module] = [Dropout(dropout_p)]
        length, width = self.beams, 1
        for out_channels in channels:
            layers += [nn.Unflatten(1, (width, length)), BeamPadding(length, pad, circular),
                       nn.Conv1d(width, out_channels, self.KERNEL, stride=self.STRIDE), nn.ReLU(), nn.Flatten(),
                       Dropout(dropout_p)]
            length, width = (length + 2 * pad - self.KERNEL) // self.STRIDE + 1, out_channels
        layers += [nn.Linear(width * length, self.features), nn.Tanh(), Dropout(dropout_p)]
        self.layers = nn.Sequential(*layers)

    def normalise(self, scan: th.Tensor) -> th.Tensor:
        """The network's input (B, N) in [0, 1] of the ranges ``scan`` (B, N).

        ``"range"`` reads a wall at 0.3 m and one at 0.5 m as 0.04 and 0.06 (of an 8 m range), and a beam that
        dropout zeroes as a wall touching the robot. ``"nearness"`` reads them as 0.74 and 0.61, and a dropped beam
        as nothing near: the resolution is where a collision is decided."""
        if self.encoding == "nearness":
            return th.exp(-scan / self.NEARNESS_SCALE)
        return scan / self.max_range

    def forward(self, scan: th.Tensor) -> th.Tensor:
        """(B, S) features of the ranges ``scan`` (B, N)."""
        return self.layers(self.normalise(scan))

    def dropout_layers(self) -> list[nn.Dropout]:
        """The dropout modules, in forward order."""
        return [m for m in self.layers if isinstance(m, nn.Dropout)]


def _box(observation_space: spaces.Dict, key: str) -> spaces.Box:
    """The ``key`` entry of the observation space, which must be a ``Box``."""
    space = observation_space[key]
    if not isinstance(space, spaces.Box):
        raise TypeError(f"observation_space[{key!r}] must be a gymnasium Box, got {space}")
    return space


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

    With a ``scan`` key in the observation space the features are ``[dropout(h), robot, scan features]`` (a
    :class:`ScanEncoder`, ``scan_encoder``; its ranges are scaled by the space's upper bound, the scan's range).
    The ``pose`` key, when present, is not read. The scan encoder is built after every other module, so the LSTM
    path draws the same initial weights for a seed with or without a scan.

    :param observation_space: ``Dict(robot=Box(5,), humans=Box(M, 7), humans_mask=Box(M,))``, optionally with
        ``scan=Box(0, range, (N,))`` (and ``pose``, ignored).
    :param lstm_hidden_size: hidden size ``H`` of each LSTM layer (default 64).
    :param n_lstm_layers: number of stacked LSTM layers (default 2).
    :param dropout_p: dropout probability during training (``p_train``), 0 disables dropout.
    :param scan_fov: the scan's field of view in degrees (the env config's ``scan.fov``): 360 wraps the
        convolutions' padding around. Read only with a scan.
    :param scan_features: ``S``, the scan encoder's output size. Read only with a scan.
    :param frame: ``"goal"`` reads the observation as it is; ``"heading"`` reads the humans and the goal in the
        robot's heading frame (:func:`to_heading_frame`; the robot part gains 2 features).
    :param scan_encoding: what the scan encoder reads of each beam (:meth:`ScanEncoder.normalise`).
    """

    h_min: th.Tensor  # (H,) buffers: the tracked feature range
    h_max: th.Tensor

    def __init__(
        self,
        observation_space: spaces.Dict,
        lstm_hidden_size: int = 64,
        n_lstm_layers: int = 2,
        dropout_p: float = 0.0,
        scan_fov: float = 360.0,
        scan_features: int = 32,
        frame: str = "goal",
        scan_encoding: str = "range",
    ) -> None:
        if frame not in FRAMES:
            raise ValueError(f"frame must be one of {list(FRAMES)}, got {frame!r}")
        robot_dim = int(_box(observation_space, "robot").shape[0]) + (2 if frame == "heading" else 0)
        human_dim = int(_box(observation_space, "humans").shape[-1])
        scan_space = _box(observation_space, SCAN_KEY) if SCAN_KEY in observation_space.spaces else None
        scan_dim = 0 if scan_space is None else scan_features
        super().__init__(observation_space, features_dim=lstm_hidden_size + robot_dim + scan_dim)
        if n_lstm_layers < 1:
            raise ValueError(f"n_lstm_layers must be >= 1, got {n_lstm_layers}")
        self.lstm_hidden_size = lstm_hidden_size
        self.robot_dim = robot_dim
        self.frame = frame
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
        # Created last, and only with a scan: the modules above draw the same initial weights with or without one.
        self.scan_encoder = None if scan_space is None else ScanEncoder(
            int(scan_space.shape[0]), float(np.max(scan_space.high)), scan_fov, dropout_p, features=scan_features,
            encoding=scan_encoding)

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
        for dropout, lstm in zip(self.input_dropouts, self.lstm_layers, strict=True):
            x = _run_lstm(cast(nn.LSTM, lstm), dropout(x))  # (B, L, H); ModuleList items are typed Module
        # h_b = x[b, n_b - 1]; rows after n_b - 1 were computed from padding but are never read.
        last = (n - 1).clamp(min=0)
        h = x[th.arange(batch, device=x.device), last]  # (B, H)
        return h * (n > 0).unsqueeze(1).to(h.dtype)  # n_b = 0  =>  h_b = 0

    def forward_with_h(self, observations: dict[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
        """Return ``(features, h)``: the features for the heads and the (pre-dropout) LSTM hidden state.

        The dropout layers run in the order of :meth:`dropout_layers` (LSTM inputs, ``h``, then the scan's): an
        external uniform stream (the ONNX runtime's) draws their masks in that order.
        """
        robot, humans = observations["robot"], observations["humans"]
        if self.frame == "heading":
            robot, humans = to_heading_frame(robot, humans)
        h = self.encode_humans(humans, observations["humans_mask"])
        parts = [self.h_dropout(h), robot]
        if self.scan_encoder is not None:
            parts.append(self.scan_encoder(observations[SCAN_KEY]))
        return th.cat(parts, dim=1), h  # (B, H + R [+ S])

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """SB3 entry point: the features vector ``[dropout(h), robot(, scan features)]`` of shape (B, H + R [+ S])."""
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
        """The extractor's dropout modules in forward order: the LSTM's, ``h``'s, then the scan encoder's."""
        scan = [] if self.scan_encoder is None else self.scan_encoder.dropout_layers()
        return [*self.input_dropouts, self.h_dropout, *scan]
