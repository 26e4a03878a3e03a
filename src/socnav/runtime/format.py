"""The socnav navigator file format: an ONNX graph of the policy network plus a JSON metadata record.
Shared by the exporter (`socnav.export`, torch) and the runtime (`socnav.runtime`, no torch).

Graph inputs (``N`` rows, ``L`` human rows, dynamic both; ``L`` may be trimmed to the real rows)::

    robot (N, 5)   humans (N, L, 7)   humans_mask (N, L)   keep_* : one dropout keep-mask per dropout layer

Each ``keep_*`` input multiplies its layer's input: ``keep = [u >= p] / (1 - p)`` for MC-dropout (``u`` uniform in
[0, 1)), all ones for the deterministic network. They are listed in ``metadata["dropout_inputs"]`` in forward order
(``per_human``: shaped (N, L, width), else (N, width)), the order of ``policy.dropout_layers()``.
Outputs: ``h`` (N, H) the LSTM state before dropout, ``mean`` (N, 2), ``log_std`` (N, 2), optionally ``value`` (N, 1).
The metadata (ONNX ``metadata_props`` key :data:`METADATA_KEY`, JSON) also carries the observation layout, the
action limits, the env config, ``p_test``, ``K``, the feature range, the safety thresholds and the socnav version.
"""

from __future__ import annotations

FORMAT_NAME = "socnav-navigator"
FORMAT_VERSION = 1
METADATA_KEY = "socnav"
OBSERVATION_INPUTS = ("robot", "humans", "humans_mask")
OUTPUTS = ("h", "mean", "log_std")
VALUE_OUTPUT = "value"

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "METADATA_KEY", "OBSERVATION_INPUTS", "OUTPUTS", "VALUE_OUTPUT"]
