"""The config models of the network impairment stage (``link.impairment``; what each option
does: ``teleop_rt.com.impairment``, after Linux netem). Declarations only: the config imports
them without loading the stage (pydantic and the package's declarations only)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, model_validator

from teleop_rt.declarations import MAX_DELAY_MS
from teleop_rt.schema import StrictModel

Percent = Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)]
DelayMs = Annotated[float, Field(ge=0, le=MAX_DELAY_MS, allow_inf_nan=False)]


_Strict = StrictModel  # unknown keys refused, no boolean taken as a number
Distribution = Literal["normal", "uniform", "pareto"]  # of the delay's jitter


class GilbertElliottSpec(_Strict):
    """netem's ``loss gemodel p r 1-h 1-k``, in percent per packet."""

    p_percent: Percent  # good -> bad
    r_percent: Percent | None = None  # bad -> good; default 100 - p (netem's)
    loss_bad_percent: Percent = 100.0  # 1-h
    loss_good_percent: Percent = 0.0  # 1-k

    @property
    def r(self) -> float:
        return (100.0 - self.p_percent if self.r_percent is None else self.r_percent) / 100.0

    @model_validator(mode="after")
    def _leaves_bad(self) -> GilbertElliottSpec:
        if self.p_percent > 0 and self.r == 0:
            raise ValueError("r_percent must be > 0: a bad state that is never left loses all")
        return self


class DelayStepSpec(_Strict):
    """From ``at_s`` (sender time) on, the base delay is ``delay_ms``."""

    at_s: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    delay_ms: DelayMs


class ImpairmentSpec(_Strict):
    """What the network does to each packet, one way (both directions draw their own)."""

    seed: Annotated[int, Field(ge=0)] = 0
    delay_ms: DelayMs = 0.0
    jitter_ms: DelayMs = 0.0
    distribution: Distribution = "normal"
    correlation_percent: Annotated[float, Field(ge=0, lt=100, allow_inf_nan=False)] = 0.0
    loss_percent: Percent = 0.0
    gilbert_elliott: GilbertElliottSpec | None = None
    duplicate_percent: Percent = 0.0
    reorder_percent: Percent = 0.0
    reorder_gap: Annotated[int, Field(ge=1)] = 1
    delay_step: DelayStepSpec | None = None
    trace: Path | None = None
    max_delay_ms: Annotated[float, Field(gt=0, le=MAX_DELAY_MS, allow_inf_nan=False)] = 1000.0

    @model_validator(mode="after")
    def _consistent(self) -> ImpairmentSpec:
        if self.loss_percent and self.gilbert_elliott is not None:
            raise ValueError("give loss_percent or gilbert_elliott, not both")
        if self.trace is not None:
            # a field at its default is no conflict: a log's config attachment writes them all
            fields = type(self).model_fields
            others = [k for k in _MODEL_FIELDS if getattr(self, k) != fields[k].default]
            if others:
                raise ValueError(f"trace replaces {', '.join(others)}: give one or the other")
        steps = [self.delay_ms] + ([self.delay_step.delay_ms] if self.delay_step else [])
        if max(steps) > self.max_delay_ms:
            raise ValueError(f"a delay of {max(steps):g} ms is beyond max_delay_ms")
        if self.reorder_percent and self.delay_ms == 0:
            raise ValueError("reorder_percent needs a delay_ms to overtake (as netem's reorder)")
        return self

    def with_paths_resolved(self, base_dir: Path) -> ImpairmentSpec:
        """A relative ``trace`` made relative to ``base_dir`` (the config file's folder)."""
        if self.trace is None or self.trace.is_absolute():
            return self
        return self.model_copy(update={"trace": (base_dir / self.trace).resolve()})


_MODEL_FIELDS = ("delay_ms", "jitter_ms", "distribution", "correlation_percent", "loss_percent",
                 "gilbert_elliott", "duplicate_percent", "reorder_percent", "reorder_gap",
                 "delay_step")  # fmt: skip
