"""One to_dict / from_dict for the models' config dataclasses, which travel inside weights and checkpoints."""
from __future__ import annotations

from dataclasses import asdict
from typing import Any, ClassVar, TypeVar

C = TypeVar("C", bound="Config")


class Config:
    """Mixin for a config dataclass: JSON-able dict out; in, lists become tuples again, keys this version
    does not know are ignored, and `legacy` fills keys that files written before a field existed lack
    (with the value those files meant, which can differ from today's default)."""

    legacy: ClassVar[dict[str, Any]] = {}

    def to_dict(self) -> dict:
        return asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls: type[C], d: dict) -> C:
        known = cls.__dataclass_fields__  # type: ignore[attr-defined]
        fields = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in known}
        for k, v in cls.legacy.items():
            fields.setdefault(k, v)
        return cls(**fields)
