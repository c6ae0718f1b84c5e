"""The ranges of the training config's fields, and each field's flat key.

The training config is a tree of small frozen dataclasses (:class:`splat_train.config.TrainConfig`
and the configs beside the strategies and training parts); what a user writes (``--config``
JSON, the ``python -m splat_train`` flags, the workflow's ``train:`` keys, ``train.json``'s
``config``) is one flat dict whose keys each name exactly one field of the tree. A config class
says how its fields are spelt there: ``flat_prefix`` before every field name, or ``flat_names``
for a field spelt otherwise (``DropoutConfig.rate`` is ``dropout_rate``). Light on purpose: the
workflow reads the recipes without importing torch.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

from runtime.checks import Range, check_fields

__all__ = ["COUNT", "ITERATION", "RATE", "WEIGHT", "POSITIVE", "FRACTION", "SEED", "THREADS",
           "flat_names", "check", "field_docs"]

# Iteration counts and periods: a count >= 1, a start or a period where 0 means never >= 0.
COUNT = Range(1, integer=True)
ITERATION = Range(0, integer=True)
# Adam step sizes (a rate of 0 freezes the parameter) and loss weights / thresholds (0 = off).
RATE = Range(0.0)
WEIGHT = Range(0.0)
POSITIVE = Range(0.0, lo_open=True)
# Probabilities, fractions of the run, opacities.
FRACTION = Range(0.0, 1.0)
# torch.manual_seed's range: an unsigned 64-bit integer.
SEED = Range(0, 2**64 - 1, integer=True)
# Thread counts: 0 = the library's own choice.
THREADS = Range(0, integer=True)


def flat_names(cls: type) -> dict[str, str]:
    """{field name: flat key} of the config dataclass ``cls``'s own values (fields holding a
    nested config are left out): ``cls.flat_names`` where given, else ``cls.flat_prefix`` +
    the field name."""
    own = getattr(cls, "flat_names", {}) or {}
    prefix = getattr(cls, "flat_prefix", "") or ""
    return {f.name: own.get(f.name, prefix + f.name) for f in dataclasses.fields(cls)
            if not dataclasses.is_dataclass(f.default) and f.default_factory is dataclasses.MISSING}


def check(obj: Any) -> None:
    """:func:`runtime.checks.check_fields` of ``obj``, its error naming the field by its flat key
    (the spelling the user wrote)."""
    try:
        check_fields(obj)
    except ValueError as exc:
        msg = str(exc)
        for field, key in flat_names(type(obj)).items():
            if msg.startswith(field + " "):
                raise ValueError(key + msg[len(field):]) from None
        raise


_ENTRY = re.compile(r"^ {8}(\w+(?:, \w+)*): (.*)$")


def field_docs(cls: type) -> dict[str, str]:
    """{field name: its description} from the ``Attributes:`` section of ``cls``'s docstring
    (Google style: ``name: text`` indented by 8, continuation lines deeper; ``a, b: text``
    describes both), each description on one line (the help of the flag that sets it)."""
    docs: dict[str, str] = {}
    current: list[str] = []
    inside = False
    for line in (cls.__doc__ or "").splitlines():
        if line.strip() == "Attributes:":
            inside = True
            continue
        if not inside:
            continue
        m = _ENTRY.match(line)
        if m:
            current = m.group(1).split(", ")
            for name in current:
                docs[name] = m.group(2).strip()
        elif line.startswith(" " * 12) and current:
            for name in current:
                docs[name] += " " + line.strip()
        elif line.strip():
            break
    return docs
