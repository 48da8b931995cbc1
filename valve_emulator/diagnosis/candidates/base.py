r"""The small bases every candidate physics implements, one per kind, and the registry that finds them by name.

A candidate is one piece of physics the nominal model may have left out. It sits in one *slot* of the
signal chain

    OP --[actuator]--> --[valve]--> MV --[characteristic]--> --[limit]--> flow --[linear plant, θ]--> --[output]--> PV

and knows the grids of its parameters worth trying (from the data: coarse, optionally a denser global scan,
and a local refinement) and how to say its parameters in the words of the JSON findings. What else it knows
depends on its *kind* (:class:`Kind`), i.e. where it acts; each kind has its own small base:

:class:`ChainCandidate` (``actuator``, ``valve``, ``characteristic``, ``limit`` slots)
    transforms the signal at its slot for a whole batch of parameter rows at once (:meth:`~ChainCandidate.apply`;
    the search is vectorised over candidates, never a Python loop over them).
:class:`DelayCandidate` (``delay`` slot)
    the dead time, part of every linear fit (every fit searches it on a grid); nothing to transform.
:class:`OutputCandidate` (``output`` slot)
    acts after the plant, on what is measured (a quantised measurement, an external oscillating disturbance
    added to PV). The chain ends at the flow, so these cannot be a transform of it; instead
    :meth:`~OutputCandidate.adjust` says, for the linear part's current prediction, which PV the linear part
    should be fitted to, :meth:`~OutputCandidate.predict` what the whole model predicts for the record and
    :meth:`~OutputCandidate.simulate` what it predicts without one (backfitting, see
    :mod:`~valve_emulator.diagnosis.fit.backfit`).
:class:`LoopCandidate` (``loop`` slot)
    explains a cycle through the loop itself, not the OP → PV path (aggressive ``tuning``): it adds nothing
    to the replayed model, so it is not searched; :meth:`~LoopCandidate.assess` judges it on the final model.

Besides what it computes, a candidate declares what the rest of the package does with a finding of it:
:attr:`~Candidate.cause_rank` (where it ranks among the causes of a "no stiction" answer),
:attr:`~Candidate.needs_span` (whether plant data must know OP's travel span to search it) and
:attr:`~Candidate.twin_role` (what it becomes in the twin's loop config, :class:`TwinRole`). A new candidate is
one module in this package: it subclasses the base of its kind and calls :func:`register`; the package imports
every module in it (see its ``__init__``), and the reason codes
(:class:`~valve_emulator.diagnosis.answers.Reason`) and the JSON Schema take its name from :func:`registry`.
"""

from __future__ import annotations

import inspect
from abc import ABC, abstractmethod
from dataclasses import dataclass
from enum import StrEnum
from typing import ClassVar, Final

import numpy as np

from valve_emulator.physics.signal_chain import DEFAULT_RANGEABILITY

__all__ = ["SLOTS", "KINDS", "Kind", "TwinRole", "Candidate", "ChainCandidate", "DelayCandidate", "OutputCandidate",
           "LoopCandidate", "ChainContext", "register", "registry", "get"]

#: Positions, in signal order. At most one candidate per slot is active in a model.
SLOTS: Final = ("actuator", "valve", "characteristic", "limit", "delay", "output", "loop")


class Kind(StrEnum):
    """Where a candidate acts (see the module docstring); its value is the word used in messages."""

    CHAIN = "chain"
    DELAY = "delay"
    OUTPUT = "output"
    LOOP = "loop"


#: The slots each kind may occupy (keyed by the kind's word).
KINDS: Final = {Kind.CHAIN.value: ("actuator", "valve", "characteristic", "limit"), Kind.DELAY.value: ("delay",),
                Kind.OUTPUT.value: ("output",), Kind.LOOP.value: ("loop",)}


class TwinRole(StrEnum):
    """What a finding becomes in the twin, the loop config ``diagnose --twin`` writes
    (:mod:`~valve_emulator.diagnosis.report.twin`); its value names the keys it writes.

    Each role sits in one slot and reads the finding's parameters by name (:attr:`slot`, :attr:`reads`): the
    twin of a valve band takes ``S``, and ``J`` when the candidate has one (0 otherwise: a deadband). A candidate
    without a role (``twin_role = None``: a quantised PV, a new valve model the loop config has no keys for)
    is left out of the twin, and the twin's header says so.
    """

    VALVE_BAND = "valve.S, valve.J"
    CHARACTERISTIC = "valve.characteristic, valve.rangeability"
    ACTUATOR_LAG = "valve.actuator_lag"
    DEAD_TIME = "plant.delay"
    FLOW_LIMITS = "valve.flow_limits"
    DISTURBANCE = "plant.disturbance"

    @property
    def slot(self) -> str:
        """The slot a candidate with this role sits in."""
        return _TWIN_SLOTS[self]

    @property
    def reads(self) -> tuple[str, ...]:
        """The parameter names the twin reads (``J`` of a valve band is optional)."""
        return _TWIN_READS[self]


_TWIN_SLOTS: Final = {TwinRole.VALVE_BAND: "valve", TwinRole.CHARACTERISTIC: "characteristic",
                      TwinRole.ACTUATOR_LAG: "actuator", TwinRole.DEAD_TIME: "delay", TwinRole.FLOW_LIMITS: "limit",
                      TwinRole.DISTURBANCE: "output"}
_TWIN_READS: Final = {TwinRole.VALVE_BAND: ("S",), TwinRole.CHARACTERISTIC: ("kind", "R"),
                      TwinRole.ACTUATOR_LAG: ("tau",), TwinRole.DEAD_TIME: (), TwinRole.FLOW_LIMITS: ("lo", "hi"),
                      TwinRole.DISTURBANCE: ("period", "amplitude", "phase")}

#: What a candidate of each kind must implement besides the common methods.
_REQUIRED: Final = {Kind.CHAIN: ("apply",), Kind.DELAY: (), Kind.OUTPUT: ("adjust", "predict", "simulate"),
                    Kind.LOOP: ("assess",)}


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
    stops : where 0 and 100 % travel lie on the chain's input scale (the search's frame, see
        :attr:`~valve_emulator.diagnosis.fit.frame.Frame.stops`); the characteristic and limit slots act on
        travel, ``100 (x − stops[0]) / (stops[1] − stops[0])``.
    """

    dt: float
    op: np.ndarray
    op_span: float
    valve_model: str = "kano"
    rest_samples: int = 1
    characteristic: tuple[str, float] = ("linear", DEFAULT_RANGEABILITY)
    tau_plant: float = 10.0
    delay: float = 0.0
    pv: np.ndarray | None = None
    y_scale: float = 1.0
    y_mean: float = 0.0
    window: tuple[int, int] = (0, 0)
    residual: np.ndarray | None = None
    stops: tuple[float, float] = (0.0, 100.0)

    def travel(self, x: np.ndarray) -> np.ndarray:
        """The chain's signal ``x`` on the travel scale of the characteristic and limit slots (0–100 %)."""
        lo, hi = self.stops
        return np.asarray(x, dtype=float) if (lo, hi) == (0.0, 100.0) else (np.asarray(x, dtype=float) - lo) * (
            100.0 / (hi - lo))

    def from_travel(self, v: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`travel`."""
        lo, hi = self.stops
        return v if (lo, hi) == (0.0, 100.0) else lo + np.asarray(v, dtype=float) * ((hi - lo) / 100.0)


class Candidate(ABC):
    """What every candidate knows: its place, its parameters, their grids and how to say them.

    Class attributes
    ----------------
    name : the word used in findings (``"stiction"``, ...).
    slot : one of :data:`SLOTS`; it fixes the candidate's :attr:`kind`.
    param_names : names of the parameter vector's entries, in order.
    dims : which parameters are OP differences (``"op"``: a band, a jump) or OP levels (``"op_level"``: a
        limit, on the travel scale of :meth:`ChainContext.travel`), converted from the search's frame to OP's
        units (:mod:`~valve_emulator.diagnosis.fit.frame`); the others (times, PV quantities,
        labels) need no conversion.
    n_params : parameters counted by BIC (may differ from ``len(param_names)`` when a name is a label,
        e.g. the characteristic's type).
    cause_rank : where a finding of it ranks among the causes of a "no stiction" answer on plant data, lowest
        first (:mod:`~valve_emulator.diagnosis.assess.decision`); None (the default): it never names that
        cause (valve friction is the stiction answer itself; ``tuning`` is judged on its own).
    needs_span : it acts on travel levels (0 and 100 % at the travel stops), so plant data search it only when
        OP's travel span is known, or when :meth:`shows_without_span` says OP places it anyway.
    twin_role : what a finding of it becomes in the twin (:class:`TwinRole`); None: the twin leaves it out.
    """

    name: ClassVar[str]
    slot: ClassVar[str]
    param_names: ClassVar[tuple[str, ...]]
    n_params: ClassVar[int]
    dims: ClassVar[dict[str, str]] = {}
    cause_rank: ClassVar[int | None] = None
    needs_span: ClassVar[bool] = False
    twin_role: ClassVar[TwinRole | None] = None

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

    def bounds(self, ctx: ChainContext) -> dict[str, tuple[float | None, float | None]]:
        """The ends of the range the search explores, per parameter name, where the truth may lie beyond them.

        An estimate on such an end is not a value but a bound ("R ≥ 400"): the findings say so. An end that is
        a limit of the physics itself (a jump of 0, a dead time of 0) is no search edge: None. Default: none
        declared. :meth:`describe` is handed the parameters whose estimate sits on one (``edges``), to say them as
        bounds (:func:`said`).
        """
        return {}

    def search_range(self, ctx: ChainContext) -> tuple[np.ndarray, np.ndarray]:
        """Per parameter (in :attr:`param_names`' order), the lower and upper ends of the range searched:
        :meth:`bounds`, ``±inf`` where none is declared."""
        ends = self.bounds(ctx)
        lo = np.array([-np.inf if ends.get(k, (None, None))[0] is None else ends[k][0] for k in self.param_names])
        hi = np.array([np.inf if ends.get(k, (None, None))[1] is None else ends[k][1] for k in self.param_names])
        return lo, hi

    def burn_in(self, ctx: ChainContext) -> int:
        """Samples after which this candidate's unknown initial state no longer matters (default 0).

        The search starts scoring every model after the largest burn-in of the library, so that all
        candidates are compared on the same samples.
        """
        return 0

    def applicable(self, ctx: ChainContext) -> bool:
        """Whether the data can show this physics at all (e.g. a quantiser needs a PV on few levels)."""
        return True

    def shows_without_span(self, op: np.ndarray) -> bool:
        """For a candidate that :attr:`needs_span`: whether the recorded OP (in its own units) places it even
        though the travel span is unknown (default: no)."""
        return False

    def identity(self) -> np.ndarray | None:
        """Parameter vector that leaves the signal unchanged (None when there is none)."""
        return None

    @abstractmethod
    def parameters(self, p: np.ndarray) -> dict:
        """The JSON ``parameters`` dict for one parameter vector (its keys are part of the JSON output)."""

    @abstractmethod
    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        """A short phrase for the verdict, e.g. ``"valve stiction: S ≈ 4.8 %, J ≈ 2.1 % (undershoot)"``;
        ``p`` in OP's units (see :mod:`~valve_emulator.diagnosis.fit.frame`), ``units`` their label after a
        number, with its space (``" %"``, ``" mA"``, ``" OP units"``); ``edges`` the parameters whose estimate
        sits on an edge of the range searched (name → (``"≥"`` or ``"≤"``, the edge), in the units of ``p``):
        such a parameter is said as the bound (:func:`said`), never as a value."""

    @property
    def kind(self) -> Kind:
        """The candidate's kind, from its slot (:data:`KINDS`)."""
        return next(Kind(k) for k, slots in KINDS.items() if self.slot in slots)


def said(symbol: str, name: str, value: float, spec: str, edges: dict | None, unit: str = "") -> str:
    """One parameter in a finding's phrase: ``"τ ≈ 4.2 s"``, or, when ``name`` sits on an edge of the range
    searched (``edges``, as :meth:`Candidate.describe` takes them), the bound alone: ``"τ ≥ 30 s"``."""
    if edges and name in edges:
        sign, edge = edges[name]
        return f"{symbol} {sign} {edge:{spec}}{unit}"
    return f"{symbol} ≈ {value:{spec}}{unit}"


class ChainCandidate(Candidate):
    """A candidate that transforms the chain signal at its slot (``actuator``, ``valve``, ``characteristic``,
    ``limit``)."""

    #: Indices of threshold parameters: their cost is flat-bottomed (piecewise constant at fine scale), so
    #: the search takes the middle of the flat bottom along each of them (see :meth:`line`).
    threshold_axes: ClassVar[tuple[int, ...]] = ()
    #: The parameters are positive and the cost is smooth in them, and they trade off against the plant's poles
    #: (an actuator lag against a plant time constant): the fitter polishes them jointly with the poles, on a
    #: log scale (:meth:`~valve_emulator.diagnosis.fit.fitter.Fitter.joint_polish`).
    joint_with_poles: ClassVar[bool] = False
    #: The physics may begin part-way through a record (a valve that starts to stick): the search then also
    #: fits it as acting only from an onset time on
    #: (:class:`~valve_emulator.diagnosis.explain.onset.LateOnset`).
    may_start_late: ClassVar[bool] = False
    #: Every value :meth:`apply` returns lies within 0–100 % or is NaN, whatever its input (a valve's MV: the state
    #: machines clip it): the chain then skips the travel stops' check of the nominal linear characteristic after
    #: it (:func:`~valve_emulator.diagnosis.fit.chain.run_chain`), which would find nothing to clip.
    output_in_range: ClassVar[bool] = False

    @abstractmethod
    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """Transform the chain signal at this slot.

        ``x`` is (T,) shared by all parameter rows, or (T, n) one column per row; ``params`` is
        (n, len(param_names)). Returns (T, n).
        """

    def line(self, ctx: ChainContext, best: np.ndarray, axis: int) -> np.ndarray:
        """Rows varying parameter ``axis`` finely around ``best`` (for :attr:`threshold_axes` only; a candidate
        with threshold axes overrides it)."""
        return best[None, :]


class DelayCandidate(Candidate):
    """The dead time: its parameter is the linear part's own, searched inside every linear fit."""

    twin_role: ClassVar[TwinRole | None] = TwinRole.DEAD_TIME


class OutputCandidate(Candidate):
    """A candidate acting after the plant, on the measured PV (see the module docstring)."""

    @abstractmethod
    def adjust(self, y: np.ndarray, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext
               ) -> tuple[np.ndarray, np.ndarray]:
        """``(target, params)`` for scaled PV ``y`` and the linear part's prediction ``y_lin``.

        ``target`` is what the linear part is fitted to next; ``params`` is the row with the entries this
        candidate fits internally (by least squares on ``ctx.window``) filled in.
        """

    @abstractmethod
    def predict(self, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """What the whole model predicts for the recorded (scaled) PV, given the linear part's ``y_lin``."""

    @abstractmethod
    def simulate(self, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """What the whole model predicts (scaled PV) without a recorded PV (a new OP, ``ctx.op``; ``ctx.pv`` is
        None), given the linear part's ``y_lin``."""

    def regressors(self, params: np.ndarray, ctx: ChainContext) -> np.ndarray | None:
        """Additive terms only: the (T, m) regressors the term is linear in, so the linear part and the term
        can be fitted jointly by least squares instead of by backfitting (None: not additive)."""
        return None


class LoopCandidate(Candidate):
    """A candidate judged on the loop, not fitted into the OP → PV model (see the module docstring)."""

    @abstractmethod
    def assess(self, **data):
        """Judge the candidate on a finished diagnosis (see the candidate's module)."""


_REGISTRY: dict[str, Candidate] = {}


def register(candidate: Candidate) -> Candidate:
    """Add a candidate instance to the library under its ``name`` (the last registration wins).

    Raises ValueError for a declaration the package could not act on: a name that is no lower-case identifier
    (it is a reason code and a JSON word), an unknown slot, a method its kind needs, or a twin role in another
    slot or reading a parameter the candidate does not have, or a ``describe`` that does not take ``units`` and
    ``edges`` (the findings hand it both).
    """
    name = candidate.name
    if not (isinstance(name, str) and name.isidentifier() and name == name.lower()):
        raise ValueError(f"candidate {name!r}: its name must be a lower-case identifier (a reason code)")
    if candidate.slot not in SLOTS:
        raise ValueError(f"candidate {name!r}: slot must be one of {', '.join(SLOTS)}, got {candidate.slot!r}")
    missing = [m for m in _REQUIRED[candidate.kind] if not callable(getattr(candidate, m, None))]
    if missing:
        raise ValueError(f"candidate {name!r}: a {candidate.kind} candidate (slot {candidate.slot!r}) "
                         f"must implement {', '.join(missing)}")
    taken = inspect.signature(candidate.describe).parameters
    lacking = [k for k in ("units", "edges") if k not in taken
               and not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in taken.values())]
    if lacking:
        raise ValueError(f"candidate {name!r}: describe(self, p, nominal=None, units=' %', edges=None) must take "
                         f"{' and '.join(lacking)} (the findings hand them)")
    role = candidate.twin_role
    if role is not None and (role.slot != candidate.slot or not set(role.reads) <= set(candidate.param_names)):
        raise ValueError(f"candidate {name!r}: twin role {role.name} needs slot {role.slot!r} and the parameters "
                         f"{', '.join(role.reads) or '(none)'}; it has slot {candidate.slot!r} and "
                         f"{', '.join(candidate.param_names)}")
    _REGISTRY[name] = candidate
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
