r"""The tiny base every candidate physics implements, and the registry that finds them by name.

A candidate is one piece of physics the nominal model may have left out. It sits in one *slot* of the
signal chain

    OP --[actuator]--> --[valve]--> MV --[characteristic]--> --[limit]--> flow --[linear plant, θ]--> --[output]--> PV

and knows three things: the grids of its parameters worth trying (from the data: coarse, optionally a
denser global scan, and a local refinement), how to transform the
signal at its slot for a whole batch of parameter vectors at once (the search is vectorised over
candidates, never a Python loop over them), and how to say its parameters in the words of the issue.
The dead time lives inside the linear fit (every fit searches it on a grid, see ``search.py``); its
candidate declares ``slot = "delay"`` and the transform is the identity.

Candidates come in four *kinds* (:data:`KINDS`), by where they act:

``chain``
    transforms the signal at a chain slot (``actuator``, ``valve``, ``characteristic``, ``limit``) for a
    batch of parameter rows at once: :meth:`Candidate.apply`.
``delay``
    the dead time, part of every linear fit.
``output``
    acts after the plant, on what is measured (``output`` slot: a quantised measurement, an external
    oscillating disturbance added to PV). The chain ends at the flow, so these cannot be a transform of it;
    instead :meth:`Candidate.adjust` says, for the linear part's current prediction, which PV the linear part
    should be fitted to, and :meth:`Candidate.predict` what the whole model predicts (backfitting, see
    :mod:`~valve_emulator.diagnosis.fit.backfit`).
``loop``
    explains a cycle through the loop itself, not the OP → PV path (aggressive ``tuning``): it adds nothing
    to the replayed model, so it is not searched; :meth:`Candidate.assess` judges it on the final model.

New candidates subclass :class:`Candidate` in their own module and call :func:`register`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar, Final

import numpy as np

__all__ = ["SLOTS", "KINDS", "Candidate", "ChainContext", "register", "registry", "get"]

#: Positions, in signal order. At most one candidate per slot is active in a model.
SLOTS: Final = ("actuator", "valve", "characteristic", "limit", "delay", "output", "loop")
#: What a candidate acts on (see the module docstring), and the slots each kind may occupy.
KINDS: Final = {"chain": ("actuator", "valve", "characteristic", "limit"), "delay": ("delay",),
                "output": ("output",), "loop": ("loop",)}


@dataclass(frozen=True)
class ChainContext:
    """What a candidate may know about the data and the nominal model when it builds its grid.

    Attributes
    ----------
    dt : sample time (s).
    op : controller output (% travel), the chain's input.
    op_span : robust OP range, 99.5th minus 0.5th percentile (% travel).
    valve_model : stiction state machine of the nominal valve (``"kano"``, ...).
    rest_samples : rest criterion for that machine.
    characteristic : nominal flow characteristic ``(kind, rangeability)``.
    tau_plant : dominant time constant of the current linear part (s); bounds the actuator-lag grid.
    delay : current dead time (s).
    pv : recorded PV (engineering units), for ``output`` candidates (None when not given).
    y_scale, y_mean : how the fit scales PV, ``y = (pv − y_mean) / y_scale``.
    window : ``(w0, w1)``, the samples the linear part is fitted on.
    residual : scaled PV minus the prediction of the model being extended (None when not known).
    """

    dt: float
    op: np.ndarray
    op_span: float
    valve_model: str = "kano"
    rest_samples: int = 1
    characteristic: tuple[str, float] = ("linear", 50.0)
    tau_plant: float = 10.0
    delay: float = 0.0
    pv: np.ndarray | None = None
    y_scale: float = 1.0
    y_mean: float = 0.0
    window: tuple[int, int] = (0, 0)
    residual: np.ndarray | None = None


class Candidate(ABC):
    """One piece of left-out physics: a parameter grid and a batched signal transform.

    Class attributes
    ----------------
    name : the word used in findings (``"stiction"``, ...).
    slot : one of :data:`SLOTS`.
    param_names : names of the parameter vector's entries, in order.
    n_params : parameters counted by BIC (may differ from ``len(param_names)`` when a name is a label,
        e.g. the characteristic's type).
    """

    name: ClassVar[str]
    slot: ClassVar[str]
    param_names: ClassVar[tuple[str, ...]]
    n_params: ClassVar[int]
    #: One of :data:`KINDS`; the default follows from the slot.
    kind: ClassVar[str | None] = None
    #: Indices of threshold parameters: their cost is flat-bottomed (piecewise constant at fine scale), so
    #: the search takes the middle of the flat bottom along each of them (see :meth:`line`).
    threshold_axes: ClassVar[tuple[int, ...]] = ()

    @abstractmethod
    def grid(self, ctx: ChainContext) -> np.ndarray:
        """Coarse grid of parameter vectors, shape (n, len(param_names))."""

    def scan(self, ctx: ChainContext) -> np.ndarray | None:
        """An optional global grid finer than :meth:`grid`, searched once the linear dynamics are chosen.

        For parameters whose cost is rough at fine scale (stiction's S) a coarse grid can miss the basin;
        the scan is denser along such directions. None (the default) skips this stage.
        """
        return None

    @abstractmethod
    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        """A finer grid around ``best`` (which it must contain)."""

    def profile_grid(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        """Rows around ``best`` over which the cost is profiled for the 95 % intervals (default: :meth:`refine`).

        It must reach beyond where the cost crosses the interval's bound, or the interval is cut at its edge.
        """
        return self.refine(ctx, best)

    def burn_in(self, ctx: ChainContext) -> int:
        """Samples after which this candidate's unknown initial state no longer matters (default 0).

        The search starts scoring every model after the largest burn-in of the library, so that all
        candidates are compared on the same samples.
        """
        return 0

    def line(self, ctx: ChainContext, best: np.ndarray, axis: int) -> np.ndarray:
        """Rows varying parameter ``axis`` finely around ``best`` (for ``threshold_axes`` only)."""
        raise NotImplementedError(f"{self.name} has no threshold axes")

    @abstractmethod
    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """Transform the chain signal at this slot.

        ``x`` is (T,) shared by all parameter rows, or (T, n) one column per row; ``params`` is
        (n, len(param_names)). Returns (T, n).
        """

    @abstractmethod
    def parameters(self, p: np.ndarray) -> dict:
        """The JSON ``parameters`` dict for one parameter vector (keys fixed by the issue)."""

    @abstractmethod
    def describe(self, p: np.ndarray, nominal: dict | None = None) -> str:
        """A short phrase for the verdict, e.g. ``"valve stiction: S ≈ 4.8 %, J ≈ 2.1 % (undershoot)"``."""

    # -- output and loop candidates --------------------------------------------------------------------------
    def applicable(self, ctx: ChainContext) -> bool:
        """Whether the data can show this physics at all (e.g. a quantiser needs a PV on few levels)."""
        return True

    def adjust(self, y: np.ndarray, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext
               ) -> tuple[np.ndarray, np.ndarray]:
        """``output`` kind: ``(target, params)`` for scaled PV ``y`` and the linear part's prediction ``y_lin``.

        ``target`` is what the linear part is fitted to next; ``params`` is the row with the entries this
        candidate fits internally (by least squares on ``ctx.window``) filled in.
        """
        raise NotImplementedError(f"{self.name} is a {self.category} candidate, not an output one")

    def predict(self, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """``output`` kind: what the whole model predicts for the recorded (scaled) PV."""
        raise NotImplementedError(f"{self.name} is a {self.category} candidate, not an output one")

    def regressors(self, params: np.ndarray, ctx: ChainContext) -> np.ndarray | None:
        """``output`` kind, additive terms only: the (T, m) regressors the term is linear in, so the linear
        part and the term can be fitted jointly by least squares instead of by backfitting (None: not
        additive)."""
        return None

    def assess(self, **data):
        """``loop`` kind: judge the candidate on a finished diagnosis (see the candidate's module)."""
        raise NotImplementedError(f"{self.name} is a {self.category} candidate, not a loop one")

    # -- conveniences shared by all candidates -------------------------------------------------------------
    @property
    def category(self) -> str:
        """The candidate's kind (:data:`KINDS`), from :attr:`kind` or its slot."""
        if self.kind is not None:
            return self.kind
        return next(k for k, slots in KINDS.items() if self.slot in slots)

    def identity(self) -> np.ndarray | None:
        """Parameter vector that leaves the signal unchanged (None when there is none)."""
        return None


_REGISTRY: dict[str, Candidate] = {}


def register(candidate: Candidate) -> Candidate:
    """Add a candidate instance to the library under its ``name`` (the last registration wins)."""
    if candidate.slot not in SLOTS:
        raise ValueError(f"candidate {candidate.name!r}: slot must be one of {', '.join(SLOTS)}, "
                         f"got {candidate.slot!r}")
    if candidate.slot not in KINDS[candidate.category]:
        raise ValueError(f"candidate {candidate.name!r}: a {candidate.category} candidate cannot sit in slot "
                         f"{candidate.slot!r}")
    _REGISTRY[candidate.name] = candidate
    return candidate


def registry() -> dict[str, Candidate]:
    """The registered candidates by name (a copy; registration order)."""
    return dict(_REGISTRY)


def get(name: str) -> Candidate:
    """The candidate called ``name``; ValueError listing the known names otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown candidate physics {name!r}; known: {', '.join(_REGISTRY)}") from None
