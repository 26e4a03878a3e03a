"""A unit of work of an experiment -- train one policy, evaluate it, calibrate a safety layer -- as the runner, the
run directory and the report see it: an id, the kind of executor it needs, its parameters and its dependencies.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import Any

__all__ = ["SPEC_VERSION", "Unit"]

#: Part of every unit's spec hash: raising it makes every finished unit stale (a change of what units compute).
SPEC_VERSION = 1


@dataclass(frozen=True)
class Unit:
    """One unit of work: `kind` names its executor (registry.EXECUTORS), `params` is everything it needs (JSON).

    `id` is also the unit's directory relative to the run directory; `deps` are ids of units whose outputs it reads.
    """

    id: str
    kind: str
    params: dict[str, Any] = field(hash=False)
    deps: tuple[str, ...] = ()

    @property
    def spec_hash(self) -> str:
        """Digest of what the unit is asked to do: a finished unit with another digest is stale."""
        payload = json.dumps({"kind": self.kind, "params": self.params, "deps": list(self.deps),
                              "version": SPEC_VERSION}, sort_keys=True, default=str)
        return hashlib.sha256(payload.encode()).hexdigest()

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "kind": self.kind, "params": self.params, "deps": list(self.deps),
                "spec_hash": self.spec_hash}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Unit:
        return cls(data["id"], data["kind"], data["params"], tuple(data.get("deps", ())))
