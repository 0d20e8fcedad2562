"""The base of every config section (teleop_rt.config, its impairment and can sections):
strict keys, frozen, and no boolean where a number or a word is meant.

pydantic's lax mode reads ``true`` as 1 and ``false`` as 0 for any int or float field; in a
config that is always a slip (``peer_timeout_ms: true``), so one validator on the base refuses a
boolean for every field that does not itself take one, whatever the field, declared once. YAML
1.1 also reads an unquoted ``off`` / ``on`` / ``no`` / ``yes`` as a boolean: for a field of
words that has exactly one word YAML would have read as that boolean (``torque_limits: off``),
the word is what the user wrote and meant, so it is taken; otherwise the line says to quote it.

Importing this module stays cheap (the config imports it): pydantic only.
"""

from __future__ import annotations

import types
import typing
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, model_validator
from pydantic_core import PydanticCustomError

# the words YAML 1.1 (PyYAML's resolver) reads as each boolean, in any of its cases
YAML_BOOL_WORDS = {False: ("off", "no", "false", "n"), True: ("on", "yes", "true", "y")}


class StrictModel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    # A model-level check (pydantic allows no field 'before' validator on the tag of a tagged
    # union, such as operator.kind); its error names the key in its ctx (``BOOL_ERROR``).
    @model_validator(mode="before")
    @classmethod
    def _no_bool_for_numbers_or_words(cls, data: Any) -> Any:
        if not isinstance(data, dict) or not any(_has_bool(v) for v in data.values()):
            return data  # the common case: nothing to look at
        out = dict(data)
        for name, value in data.items():
            field = cls.model_fields.get(name) if isinstance(name, str) else None
            if field is not None and _has_bool(value):
                out[name] = _unbooled(value, field.annotation, name)
        return out


BOOL_ERROR = "bool_not_allowed"  # its ctx["key"]: the key under the section, as a user wrote it


def _has_bool(value: Any) -> bool:
    return isinstance(value, bool) or (
        isinstance(value, list) and any(isinstance(v, bool) for v in value)
    )


def _refused(key: str, message: str) -> PydanticCustomError:
    return PydanticCustomError(BOOL_ERROR, message, {"key": key})


def annotation_leaves(annotation: Any) -> list[Any]:
    """The plain types and Literal values an annotation is made of (through unions,
    Annotated, list[...] and Optional)."""
    origin = typing.get_origin(annotation)
    if origin is Literal:
        return list(typing.get_args(annotation))
    if origin is typing.Annotated:
        return annotation_leaves(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType, list):
        return [leaf for arg in typing.get_args(annotation) for leaf in annotation_leaves(arg)]
    return [annotation]


def _unbooled(value: Any, annotation: Any, key: str) -> Any:
    leaves = annotation_leaves(annotation)
    if any(leaf is bool for leaf in leaves):
        return value  # the field takes booleans (safety.enabled, can options)
    numeric = any(leaf in (int, float) for leaf in leaves)
    words = [leaf for leaf in leaves if isinstance(leaf, str)]
    if isinstance(value, list):
        if numeric:
            index = next(i for i, v in enumerate(value) if isinstance(v, bool))
            raise _refused(f"{key}.{index}", f"expected a number, got {str(value[index]).lower()}")
        return value
    if words:
        meant = [w for w in words if w.lower() in YAML_BOOL_WORDS[value]]
        if len(meant) == 1:
            return meant[0]  # torque_limits: off
        choices = ", ".join(repr(w) for w in words)
        raise _refused(
            key,
            f"got the boolean {str(value).lower()} (YAML reads an unquoted yes, no, on, off as "
            f"one); expected one of {choices}",
        )
    if numeric:
        raise _refused(key, f"expected a number, got {str(value).lower()}")
    return value  # a string, a path: pydantic refuses the boolean in its own words
