"""Per-vehicle identification and inverse control, with no I/O: the live service, replay
and the in-process experiment all feed it the same samples and get the same numbers.

Each channel (depth, pitch) has its identifier, a persistence baseline beside it, error
statistics, and an inverse controller that is allowed to act only once the identifier has
converged (``burn_in`` samples and a recent skill versus persistence of at least
``min_skill``), has not diverged since and its model passes the horizon test. Every gate is
per channel: a channel held by its own gate leaves the other channel's commands alone. One
module over 500 lines: the settings, the channel's pipeline and the vehicle's are one unit
that replay checks bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from librt.vecs import vec

from hil_service.umodel import (
    U_MODELS,
    CommandShaper,
    Estimate,
    PersistenceModel,
    PredictiveModel,
    build_model,
    option_names,
)
from hil_service.umodel.cancellation import mapped_inputs, record_prefers, reduced_model
from hil_service.umodel.dead_zone import narrow, widen, widen_beside
from hil_service.umodel.dynamics import ModelDynamics
from hil_service.umodel.finite import finite
from hil_service.umodel.lag_prior import LAG_SMOOTHING_GAIN, adds_a_slower_mode, slowest_mode
from hil_service.umodel.predictive import PredictiveInverse, PredictiveSettings, factorise
from hil_service.umodel.probe import Probe
from hil_service.umodel.scoring import ErrorStats, MultiStepStats, significant
from hil_service.umodel.structure import (
    DEAD_ZONE_CANDIDATES,
    VALIDATION_SEGMENT,
    LagChoice,
    choose_dead_zone,
    choose_input_lags,
)
from hil_service.umodel.supervisor import HorizonTest, Supervisor, steady_input
from protocols.keys import CHANNELS
from protocols.safety import SAFE_INPUTS
from protocols.samples import BallastCommand, TelemetrySample

#: A command's per-channel ``mode`` when the channel does not command from its plan:
#: nothing sent, its safe input, released to the vehicle, or probing.
NOT_FROM_THE_PLAN = frozenset({"-", "safe", "released", "probe"})

#: Consecutive samples in the horizon test's record before the input lags are chosen, or
#: at least ``LAG_CHOICE_MIN`` once the channel is asked to command (``umodel.structure``
#: needs two thirds of its record to fit and a third to validate on).
LAG_CHOICE_RECORD = 600
LAG_CHOICE_MIN = 300
#: A vehicle of phase p makes its choices ``p mod spread`` samples later (``choice_spread``).
#: A service gives its vehicles phases in the order they appear, so a fleet that started
#: together (a service restart) spreads its choices, 12-25 ms of CPU a channel, over that
#: many samples instead of stalling every vehicle's sample on one (docs/fleet.md).
LAG_CHOICE_SPREAD = 100


def choice_spread(max_vehicles: int) -> int:
    """The samples over which a service of up to ``max_vehicles`` spreads its vehicles'
    structure choices: half the fleet, so that at most two vehicles of a sample period
    choose (four channels' choices, about 0.1 s of CPU), and at least ``LAG_CHOICE_SPREAD``."""
    return max(LAG_CHOICE_SPREAD, max_vehicles // 2)


#: A tripped channel re-arms only on a record whose inputs span at least this share of the
#: actuator's limit (``_input_moved_since_trip``).
REARM_INPUT_SPAN = 0.1
#: An identifier's AR mode of modulus r is unstable for the lags' choice when rᵏ ≥ 2 over
#: k = ``VALIDATION_SEGMENT`` samples: it doubles within a segment the choice validates on.
#: A slower one (a fitted integrator, r within 1.4 % of 1) looks like an integrator there.
UNSTABLE_MODE = 2.0 ** (1.0 / VALIDATION_SEGMENT)

#: Samples between a channel's verdicts on its near pole–zero pairs
#: (``ChannelPipeline._contradicted_pairs_removed``): the record it simulates (up to 1,100
#: samples) changes by less than a quarter in between, and a verdict (roots, factorisation,
#: two filters over the record) on every ``refresh`` samples cost the service path a tenth
#: of its throughput (docs/control.md, "Near pole–zero cancellations").
LONG_RUN_CHECK = 250

#: The most input lags ``with_input_lags`` takes: 5 s of delay at 10 Hz, and the identifier's
#: regressor (3 × lags + 5 terms) still small enough for its per-sample RLS update.
MAX_INPUT_LAGS = 50

#: Model options per channel on top of each model's defaults (none: the defaults hold for
#: both channels, and a new vehicle gets no figure tuned to the emulator's).
DEFAULT_MODEL_OPTIONS: dict[str, dict[str, dict[str, Any]]] = {
    "paper": {"depth": {}, "pitch": {}},
    "dynamic": {"depth": {}, "pitch": {}},
}


#: ControlSettings field → PredictiveSettings argument: the predictive inverse's constants,
#: stored flat in a configuration under these names, defaults from PredictiveSettings.
PREDICTIVE_FIELDS: dict[str, str] = {
    "min_horizon": "min_horizon",
    "max_horizon": "max_horizon",
    "settle_band": "band",
    "max_blocks": "max_blocks",
    "move_weight": "move_weight",
    "disturbance_share": "disturbance_share",
    "refresh": "refresh",
    "cost_points": "cost_points",
    "disturbance_forecast": "disturbance_forecast",
    "horizon_arrivals": "horizon_arrivals",
    "cancel_near_pairs": "cancel_near_pairs",
}
_PREDICTIVE = PredictiveSettings()


@dataclass(frozen=True)
class ControlSettings:
    """The actuator's limits and the predictive inverse's scale-free constants.

    No horizon here: each channel's horizons come from its identified dynamics (see
    :mod:`hil_service.umodel.predictive` and docs/control.md). The predictive constants are
    :class:`PredictiveSettings`'s (their meaning and defaults live there), stored flat.
    """

    u_limit: float = 2.0  # model units, the actuator's range
    rate_limit: float = 0.5  # model units per step, as the vehicle's actuator
    min_horizon: int = _PREDICTIVE.min_horizon
    max_horizon: int = _PREDICTIVE.max_horizon
    settle_band: float = _PREDICTIVE.band
    max_blocks: int = _PREDICTIVE.max_blocks
    move_weight: float = _PREDICTIVE.move_weight
    disturbance_share: float = _PREDICTIVE.disturbance_share
    refresh: int = _PREDICTIVE.refresh
    cost_points: int = _PREDICTIVE.cost_points
    disturbance_forecast: float = _PREDICTIVE.disturbance_forecast
    horizon_arrivals: float = _PREDICTIVE.horizon_arrivals
    cancel_near_pairs: bool = _PREDICTIVE.cancel_near_pairs
    #: The horizon test's thresholds (``umodel.supervisor.HorizonTest``, docs/control.md):
    #: the model's k-step fit relative to holding the output, and relative to the mean of
    #: the outputs scored (%), both of which a channel needs before it may command (None:
    #: the mean's is not asked).
    horizon_fit: float = 20.0
    mean_fit: float | None = 20.0
    safe_input: str = "neutral"  # SAFE_INPUTS: where a tripped channel's input goes
    #: The probing excitation's amplitude, a share of ``u_limit``, for a channel asked to
    #: command whose model does not pass the horizon test (``umodel.probe``; 0: none).
    probe: float = 0.0

    def __post_init__(self) -> None:
        self.predictive()  # validates the constants
        HorizonTest(self.horizon_fit, mean_threshold=self.mean_fit)  # validates both
        if not (finite(self.probe) and 0.0 <= self.probe <= 1.0):
            raise ValueError(f"probe must be 0..1 (a share of the input range), got {self.probe}")
        if self.safe_input not in SAFE_INPUTS:
            raise ValueError(f"safe_input must be one of {SAFE_INPUTS}, got {self.safe_input!r}")

    def predictive(self) -> PredictiveSettings:
        return PredictiveSettings(
            **{arg: getattr(self, name) for name, arg in PREDICTIVE_FIELDS.items()}
        )

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ControlSettings:
        """Known fields only: a log recorded by an older controller (horizon, trajectory,
        filters) replays with this one's defaults for the rest."""
        known = {f.name for f in fields(cls)}
        data = dict(data)
        if "horizon_fit" in data:
            # Recorded with a horizon test that judged against holding alone.
            data.setdefault("mean_fit", None)
        return cls(**{k: v for k, v in data.items() if k in known})


@dataclass(frozen=True)
class PipelineSettings:
    model: str = "dynamic"
    seed: int = 0
    model_options: dict[str, dict[str, Any]] | None = None
    burn_in: int = 300
    min_skill: float = 0.0
    window: int = 500
    control: ControlSettings = field(default_factory=ControlSettings)
    #: The dynamic model's input lags chosen from each channel's record
    #: (``umodel.structure``; ``serve --input-lags auto``) unless the model options give them
    #: (``serve --input-lags N``). Unset: chosen for the dynamic model, the only one with lags.
    choose_input_lags: bool | None = None
    #: The longest telemetry gap (samples lost in a row) bridged rather than resynchronised
    #: (``ChannelPipeline._bridge``, docs/control.md, "Short gaps bridged"); 0 bridges none.
    bridge_gap: int = 5
    #: The smoothness prior on the dynamic model's input lags, given with the input lags'
    #: choice: its weight is this times the record's one-step residual share
    #: (``umodel.lag_prior``, docs/control.md); 0 gives none.
    lag_smoothing_gain: float = LAG_SMOOTHING_GAIN
    #: A rebuilt identifier (other input lags, or the prior) is judged on the record it was
    #: rebuilt from; False: on a record started afresh at the rebuild.
    rebuild_keeps_record: bool = True
    #: With the input lags' choice, an input dead zone is chosen from the record too
    #: (``umodel.structure.choose_dead_zone``): the identifier and the plan then see the
    #: input beyond it, and commands step over it (docs/control.md).
    choose_dead_zone: bool = True

    def __post_init__(self) -> None:
        gain = self.lag_smoothing_gain
        if isinstance(gain, bool) or not (
            isinstance(gain, (int, float)) and finite(gain) and gain >= 0.0
        ):
            raise ValueError(f"lag_smoothing_gain must be a number >= 0, got {gain!r}")
        if isinstance(self.bridge_gap, bool) or not (
            isinstance(self.bridge_gap, int) and self.bridge_gap >= 0
        ):
            raise ValueError(f"bridge_gap must be an integer >= 0, got {self.bridge_gap!r}")
        if self.model not in U_MODELS:
            raise ValueError(f"model must be one of {U_MODELS}, got {self.model!r}")
        if self.choose_input_lags is None:
            object.__setattr__(self, "choose_input_lags", self.model == "dynamic")
        elif self.choose_input_lags and self.model != "dynamic":
            raise ValueError(f"input lags are the dynamic model's, not the {self.model} model's")

    def replace(self, **changes: Any) -> PipelineSettings:
        return replace(self, **changes)

    def options_for(self, channel: str) -> dict[str, Any]:
        chosen = self.model_options or DEFAULT_MODEL_OPTIONS[self.model]
        return dict(chosen.get(channel, {}))

    def with_input_lag_choice(self, lags: object) -> PipelineSettings:
        """``serve --input-lags``: ``"auto"`` chooses them from each channel's record, a
        number gives them (``with_input_lags``)."""
        if lags == "auto":
            return self.replace(choose_input_lags=True)  # __post_init__ checks the model
        if isinstance(lags, str):
            try:
                lags = int(lags)
            except ValueError:
                raise ValueError(
                    f"input lags must be auto or an integer 1..{MAX_INPUT_LAGS}, got {lags!r}"
                ) from None
        return self.with_input_lags(lags)

    def with_input_lags(self, lags: object) -> PipelineSettings:
        """Every channel's identifier with ``lags`` input lags (``DynamicUModel``'s ``nb``,
        counted in samples): a vehicle whose input acts after a delay of d samples first
        responds at lag d + 1, so it needs at least d + 2 (docs/control.md, "What the
        excess is made of")."""
        if self.model != "dynamic":
            raise ValueError(f"input lags are the dynamic model's, not the {self.model} model's")
        if isinstance(lags, bool) or not (isinstance(lags, int) and 1 <= lags <= MAX_INPUT_LAGS):
            raise ValueError(f"input lags must be an integer 1..{MAX_INPUT_LAGS}, got {lags!r}")
        options = {ch: {**self.options_for(ch), "nb": lags} for ch in CHANNELS}
        return self.replace(model_options=options)

    def to_json(self) -> dict[str, Any]:
        data = asdict(self)
        data["model_options"] = {ch: self.options_for(ch) for ch in CHANNELS}
        return data

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PipelineSettings:
        """Model options the model does not take (``option_names``: a log recorded by a
        version whose identifier had them) are left out, as ``ControlSettings.from_json``
        leaves out unknown control fields, so that such a log replays."""
        data = dict(data)
        # A log recorded before the lags were chosen by default had them fixed.
        data.setdefault("choose_input_lags", False)
        # A log recorded before short gaps were bridged resynchronised after every gap.
        data.setdefault("bridge_gap", 0)
        # A log recorded before the input lags' choice gave a smoothness prior.
        data.setdefault("lag_smoothing_gain", 0.0)
        # ... and before a rebuilt identifier was judged on its record.
        data.setdefault("rebuild_keeps_record", False)
        # ... and before an input dead zone was chosen with the lags.
        data.setdefault("choose_dead_zone", False)
        control_data = dict(data.pop("control", {}))
        # ... and before the disturbance was forecast over the horizon.
        control_data.setdefault("disturbance_forecast", 0.0)
        # ... and before the horizon was capped by the response's arrival time.
        control_data.setdefault("horizon_arrivals", 0.0)
        # ... and before near pole-zero pairs the record contradicts were let go.
        control_data.setdefault("cancel_near_pairs", False)
        control = ControlSettings.from_json(control_data)
        options = data.get("model_options")
        if options:
            taken = option_names(str(data.get("model", "dynamic")))
            data["model_options"] = {
                channel: {k: v for k, v in chosen.items() if k in taken}
                for channel, chosen in options.items()
            }
        return cls(control=control, **data)


@dataclass
class StepContinuity:
    """Tells whether a sample directly follows the previous one.

    The plant period is learnt from the timestamp steps (the vehicle does not announce
    it): the lower median of the last ``window`` steps that followed on. A step longer than
    ``tolerance`` periods means samples are missing in between. The median, not the
    shortest step, so that a period that jitters is not mistaken for lost samples: with
    each timestamp within ±j of a regular grid of period P, a step is P ± 2j and a step
    over one lost sample 2P ± 2j, told apart at 1.5 P while j < P/4 (the shortest step,
    P − 2j, would separate them only while j < P/10).

    A period that changes for good to a longer one (a vehicle that goes from 5 s to 10 s
    sampling) is learnt after ``relearn`` steps in a row too long for the old period that
    agree with one another (the longest within ``tolerance`` of the shortest): those
    count as gaps until the last of them, which follows on (``period_changes``). Samples
    lost at regular intervals ``relearn`` times in a row are, from the timestamps alone,
    the same thing. A shorter period moves the median down as its steps come in.
    """

    tolerance: float = 1.5
    window: int = 9
    relearn: int = 3
    period_ms: int | None = None
    last_ms: int | None = None
    gaps: int = 0
    #: Steps back in time: the vehicle's clock restarted (counted among the gaps too).
    restarts: int = 0
    restarted: bool = False  # the last sample followed a restart
    #: Samples missing just before the last one, by the learnt period (0: it followed on,
    #: or the count is unknown: the first sample, a restart, a step back or no period yet).
    missing: int = 0
    period_changes: int = 0
    recent: list[int] = field(default_factory=list)  # the last steps that followed on
    too_long: list[int] = field(default_factory=list)  # the gap steps since the last one

    def follows(self, time_ms: int) -> bool:
        last, self.last_ms = self.last_ms, time_ms
        self.restarted = False
        self.missing = 0
        if last is None:
            return False
        step = time_ms - last
        if step <= 0:
            self.gaps += 1
            self.too_long.clear()
            if step < 0:
                self.restarts += 1
                self.restarted = True
            return False
        if self.period_ms is None or step <= self.tolerance * self.period_ms:
            self.too_long.clear()
            self._learn(step)
            return True
        self.too_long.append(step)
        if len(self.too_long) >= self.relearn:
            run = self.too_long[-self.relearn :]
            if max(run) <= self.tolerance * min(run):
                self.recent = list(run)
                self.too_long.clear()
                self._learn(None)
                self.period_changes += 1
                return True
        self.gaps += 1
        self.missing = max(round(step / self.period_ms) - 1, 1)
        return False

    def _learn(self, step: int | None) -> None:
        if step is not None:
            self.recent.append(step)
            if len(self.recent) > self.window:
                del self.recent[0]
        ordered = sorted(self.recent)
        self.period_ms = ordered[(len(ordered) - 1) // 2]


@dataclass(frozen=True, init=False)
class Decision:
    command: BallastCommand | None
    payload: dict[str, Any] | None
    reason: str

    # Written out, not generated (``init=False``): docs/compiled.md.
    def __init__(
        self, command: BallastCommand | None, payload: dict[str, Any] | None, reason: str
    ) -> None:
        object.__setattr__(self, "command", command)
        object.__setattr__(self, "payload", payload)
        object.__setattr__(self, "reason", reason)


class ChannelPipeline:
    def __init__(
        self,
        channel: str,
        settings: PipelineSettings,
        seed: int,
        phase: int = 0,
        spread: int = LAG_CHOICE_SPREAD,
    ):
        self.channel = channel
        self.settings = settings
        options = settings.options_for(channel)
        if settings.model == "dynamic":
            # Inputs normalised by the actuator's range: the same model in any input unit.
            options.setdefault("u_scale", settings.control.u_limit)
        model = build_model(settings.model, seed=seed, **options)
        assert isinstance(model, PredictiveModel)  # U_MODELS are the U-models
        self.model: PredictiveModel = model
        self._seed = seed
        self._phase = phase
        self._options = options
        #: The input dead zone's half-width chosen from the record (0: none). The
        #: identifier, the horizon test, the supervisor and the plan see every input beyond
        #: it (``narrow``); the commands sent step over it (``widen``).
        self.dead_zone = 0.0
        #: A plan's input within this of the zone's edge on its other side stays on the
        #: applied input's side (``widen_beside``): half a step of the candidate widths.
        step = DEAD_ZONE_CANDIDATES[1] - DEAD_ZONE_CANDIDATES[0]
        self._crossing_band = 0.5 * step * float(options.get("u_scale", settings.control.u_limit))
        #: With ``choose_input_lags``, the dynamic model's input lags are chosen from the
        #: first ``LAG_CHOICE_RECORD`` consecutive samples unless the options give them.
        self._lags_pending = bool(settings.choose_input_lags) and "nb" not in options
        #: With the input lags chosen, fewer output lags may be too (``_fewer_output_lags``)
        #: unless the options give them.
        self._output_lags_given = "na" in options
        self._lags_tried = False  # the choice was tried on a shorter record at the first ask
        self._choice_delay = phase % max(spread, 1)
        config = model.config()
        self._model_name: str = config["name"]  # for health, without a config() each time
        self._input_lags: int | None = config.get("nb")
        self.lag_choice: LagChoice | None = None
        # The choice's JSON, made at the first health after it: the choice does not change
        # once made, and a fleet's health asks for it every period.
        self._lag_choice_json: dict[str, object] | None = None
        self.persistence = PersistenceModel()
        self.stats = ErrorStats(burn_in=settings.burn_in, window=settings.window)
        self._long_run_wait = 0  # samples until the near pole-zero pairs are judged again
        # Multi-step accuracy: a frozen copy of the model runs free on the applied inputs
        # and restarts from the measured outputs every control horizon.
        self.multistep = MultiStepStats(window=settings.window)
        self._free_run: ModelDynamics | None = None
        self.dynamics: ModelDynamics | None = None  # the model after the last accepted step
        self._free_run_left = 0
        control = settings.control
        self.controller = PredictiveInverse(
            -control.u_limit, control.u_limit, control.rate_limit, control.predictive(), phase
        )
        self.shaper = CommandShaper(-control.u_limit, control.u_limit, control.rate_limit)
        self.probe = Probe(control.probe * control.u_limit, seed, channel)
        self.u_prev: float | None = None
        self.last: Estimate | None = None
        self.converged = False
        self.divergences = 0
        self.rejected = 0
        self.active = False
        self.resync = 0  # samples still to refill the model's history after a gap
        self.skipped = 0
        # An output that repeats the previous one bit for bit: the sampler served the same
        # reading twice, so the plant moved two steps between the previous fresh readings
        # (see ``observe``).
        self.repeats = 0
        self.refill = 0  # samples still to refill the history after a repeat (not blocking)
        self.input_reuses = 0  # samples whose input reading was the previous sample's
        self.bridged = 0  # lost samples carried across (``_bridge``)
        #: What the last decision sent on this channel (NaN: nothing), for ``_bridge``.
        self.last_command = math.nan
        self._y_seen = math.nan
        self._learnt_last = False  # the previous sample trained the model
        # Do no harm (docs/control.md): the horizon test qualifies the model to command;
        # the supervisor watches the loop while it does.
        self.horizon_test = HorizonTest(
            control.horizon_fit,
            settings.window,
            control.max_horizon + 100,
            settings.burn_in,
            control.mean_fit,
        )
        self._until_evaluation = 0  # samples to the horizon test's next evaluation
        #: Samples added to the wait after an evaluation that came off the cadence (the
        #: first, one a disqualification or the first ask calls for): a fleet whose
        #: identifiers converge, or whose control is enabled, together runs those tests
        #: together and its later ones (each over up to 1,000 samples) 1/``refresh`` of
        #: its channels a sample. A single vehicle's pipeline, phase 0, adds none.
        self._evaluation_offset = phase % settings.control.refresh  # refresh >= 1: validated
        self._on_cadence = False  # the next due evaluation is one the last one set
        #: ``decide`` asked this channel to command (control on, a setpoint) since the last
        #: sample: the horizon test runs every ``refresh`` samples then, every ``window``
        #: while nobody asks (health's verdict only).
        self._asked = False
        self._slow = False  # the last evaluation chose the slow cadence
        self._horizon_ok = False  # its last verdict
        self.qualified = False  # passed the horizon test since the last disqualifying event
        self.ever_qualified = False
        self.supervisor = Supervisor()
        self.tripped = False
        self.safe_u = 0.0
        self.restarts = 0
        self._since_trip = 0
        #: Samples from the trip until the input has reached the safe input at the rate
        #: limit: the move there is the trip's, not evidence of the input's effect.
        self._trip_ramp = 0
        self._sup_run: ModelDynamics | None = None
        # The neutral input's counterfactual: two frozen copies from the same measured
        # history, one fed the applied inputs, one the neutral input (reached at the rate
        # limit); their difference is the effect of commanding by the model's account.
        self._alt_run: ModelDynamics | None = None
        self._app_run: ModelDynamics | None = None
        self._alt_delta = math.nan  # ŷ(applied) − ŷ(neutral) for this sample
        self._alt_u = 0.0  # the counterfactual copy's input
        #: The input the counterfactual goes to: the neutral input, or, for a channel whose
        #: vehicle takes it back (safe input "release"), the input whose steady state is
        #: the setpoint by the model (``_counterfactual_input``).
        self._alt_target = 0.0
        self._sup_pred = math.nan
        self._sup_setpoint = math.nan
        self._last_saturated = False
        #: Trips and re-arms not yet published (``VehiclePipeline.take_events``).
        self.events: list[dict[str, Any]] = []

    def config(self) -> dict[str, Any]:
        return self.model.config()

    def observe(
        self,
        t: float,
        y: float,
        u_now: float,
        follows_previous: bool = True,
        input_reused: bool = False,
        sampled: bool = False,
        missing: int = 0,
    ) -> dict[str, Any] | None:
        """See ``_observe``. ``missing``: after a gap (``follows_previous`` False), how many
        samples were lost just before this one when the sample times tell (0 otherwise);
        a short gap is bridged (``_bridge``). ``input_reused``: the sampler served this
        sample's input from the reading it served the previous sample (no newer one stamped
        by the tick), so ``u_now`` may be the previous step's input: the next samples pair
        outputs with it and hold it in the history. They refill the history without
        training instead.
        ``sampled``: the sample comes from an asynchronous sampler (a periodic profile), the
        only source whose outputs can be a reading served twice; a lockstep sample is fresh
        by construction, and its repeated output a real one."""
        u_now = self.narrow(u_now)
        if not follows_previous and self._bridge(missing, u_now):
            follows_previous = True
            sampled = False  # the output two ticks apart from the last one is not a repeat
        estimate = self._observe(t, y, u_now, follows_previous, sampled)
        if input_reused and self.resync == 0:
            self.input_reuses += 1
            self.refill = max(self.refill, self.model.history_length)
            self.horizon_test.restart_run()
        return estimate

    def _observe(
        self, t: float, y: float, u_now: float, follows_previous: bool, sampled: bool
    ) -> dict[str, Any] | None:
        """Learn from one sample; None when the sample only refills the history.

        After a gap (``follows_previous`` False; also the very first sample) the input
        applied one step before ``y`` is unknown and the model's lags hold pre-gap values,
        so the next ``history_length`` samples enter the history without training the model
        (counted as ``skipped``): a missing step is skipped, never mis-aligned.
        """
        repeat = sampled and follows_previous and y == self._y_seen
        self._y_seen = y
        learnt_last = self._learnt_last
        self._learnt_last = False
        self._sup_pred = math.nan
        self._alt_delta = math.nan
        if not follows_previous or self.u_prev is None:
            self._start_resync()
        elif repeat and self.resync == 0:
            self._drop_repeat(learnt_last, y)
            return None
        self._until_evaluation -= 1
        if self.tripped:
            self._since_trip += 1
        if self.refill > 0 and self.resync == 0:
            self._refill_sample(y, u_now)
            return None
        if self.resync > 0:
            self._resync_sample(y, u_now)
            return None
        u_prev = self.u_prev
        assert u_prev is not None  # set by every sample, resynchronising ones included
        self._advance_predictions(y, u_prev)
        estimate = self.model.step(u_prev, y)
        self.horizon_test.record(y, u_prev)
        self._learnt_last = True
        if self._lags_pending and self.horizon_test.count >= LAG_CHOICE_RECORD + self._choice_delay:
            self._choose_input_lags()
        baseline = self.persistence.step(u_prev, y)
        self.u_prev = u_now
        self.last = estimate
        self._account(estimate, y, baseline.error)
        self._free_run_left -= 1
        if self._free_run_left <= 0 or (
            self._free_run is not None and self._free_run_left > self.controller.horizon
        ):
            # Due, or the horizon has become shorter than what is left of the free run:
            # the accuracy is that of the control horizon, not of a run started for a
            # longer one (a model with no input map yet gets the longest horizon).
            self._restart_free_run()
        due = self.converged and self._until_evaluation <= 0
        if due and (
            self.tripped or not self.active or not (self.qualified and self.horizon_test.full)
        ):
            self._evaluate_horizon(self._on_cadence)
        return {
            "t": t,
            "y": estimate.y,
            "y_hat": estimate.y_hat,
            "error": estimate.error,
            "alpha": list(estimate.alpha),
            "weights": list(estimate.weights),
            "model": estimate.model,
            "status": estimate.status,
            "baseline_y_hat": baseline.y_hat,
        }

    def _choose_input_lags(self) -> None:
        """Once per channel: the input lags by validation on the record
        (``umodel.structure``), and the smoothness prior the record's noise gives them
        (``umodel.lag_prior``). A choice other than the model's own rebuilds the identifier
        from the record (in order, trained where the channel trained), and the channel must
        pass the horizon test again with it; so must one whose AR part is unstable, rebuilt
        with fewer output lags (``_fewer_output_lags``). A smoothed identifier whose output
        lags carry a slower mode than the plain one's is not taken (``adds_a_slower_mode``),
        nor a prior alone while the channel commands (the choice then came under way: its
        record reached ``LAG_CHOICE_RECORD`` samples after the first command)."""
        outputs, inputs = self.horizon_test.samples()
        runs = self.horizon_test.runs()
        choice = choose_input_lags(
            outputs,
            inputs,
            float(self._options["u_scale"]),
            runs=runs,
            smoothing_gain=float(self.settings.lag_smoothing_gain),
        )
        if choice is None and len(outputs) < LAG_CHOICE_RECORD:
            return  # no choice on this short a record: the full record decides
        self._lags_pending = False
        self.lag_choice = choice
        self._lag_choice_json = None
        if choice is None:
            return
        width = 0.0
        if self.settings.choose_dead_zone and self.dead_zone == 0.0:
            width, fits = choose_dead_zone(
                outputs, inputs, float(self._options["u_scale"]), choice.lags, runs=runs
            )
            choice.dead_zone, choice.dead_zone_fits = width, fits
        smoothing = choice.smoothing
        options, model = self._structure(choice, outputs, inputs, runs, width)
        if model is not None and width > 0.0 and slowest_mode(model.dynamics().ar) >= UNSTABLE_MODE:
            # Rebuilt beyond the zone, the identifier's AR part is unstable and fewer output
            # lags do not take that out: its free runs grow without bound, so no model
            # qualifies. The structure without the zone instead.
            choice.reject_dead_zone(smoothing)
            width = 0.0
            options, model = self._structure(choice, outputs, inputs, runs, 0.0)
        if model is None:
            return
        if width > 0.0:
            self._take_dead_zone(width)
        self._options = options
        self.model = model
        self._input_lags = choice.lags
        self.dynamics = model.dynamics()
        self._free_run, self._free_run_left = None, 0
        self._sup_run = None
        self._alt_run = None
        self.controller.reset()
        if self.active:
            self.deactivate()
        # Judged again before it may command: on the record it was rebuilt from, as the
        # channel's own model is judged on the record it learnt from.
        self.disqualify(keep_record=self.settings.rebuild_keeps_record)

    def _structure(
        self,
        choice: LagChoice,
        outputs: list[float],
        inputs: list[float],
        runs: list[int],
        width: float,
    ) -> tuple[dict[str, Any], PredictiveModel | None]:
        """The identifier's options for ``choice``'s lags on the inputs beyond a dead zone
        of half-width ``width``, and the identifier rebuilt with them from the record
        (None: the channel's own stands)."""
        if width > 0.0:
            inputs = [narrow(u, width) for u in inputs]
        plain = {**self._options, "nb": choice.lags, "lag_smoothing": 0.0}
        unchanged = (
            choice.lags == self._input_lags
            and not self._options.get("lag_smoothing")
            and width == 0.0
        )
        if unchanged and self.active and choice.smoothing > 0.0:
            # Commanding on a standing verdict, with the lags chosen: the prior alone does
            # not stop it. A rebuilt identifier would be judged on a record the loop has
            # held near its setpoint, where no model's prediction has a change to show.
            choice.withhold_smoothing()
        record = (outputs, inputs, runs)
        model = None if unchanged else self._rebuilt(plain, *record)
        fewer = self._fewer_output_lags(plain, self.model if model is None else model, record)
        if fewer is not None:
            plain = {**plain, "na": fewer[0]}
            model = fewer[1]
            choice.output_lags = fewer[0]
        options = plain
        if choice.smoothing > 0.0:
            smoothed = {**plain, "lag_smoothing": choice.smoothing}
            smooth = self._rebuilt(smoothed, *record)
            reference = self.model if model is None else model
            if adds_a_slower_mode(reference.dynamics().ar, smooth.dynamics().ar):
                choice.reject_smoothing()
            else:
                options, model = smoothed, smooth
        return options, model

    def _take_dead_zone(self, width: float) -> None:
        """From now on the channel sees inputs beyond a dead zone of half-width ``width``:
        its record and its last input are narrowed, and the plan's inputs range over what
        is left of the actuator beyond the zone."""
        self.dead_zone = width
        self.horizon_test.narrow_inputs(width)
        if self.u_prev is not None:
            self.u_prev = self.narrow(self.u_prev)
        self.last_command = self.narrow(self.last_command)
        control = self.settings.control
        limit = control.u_limit - width
        self.controller = PredictiveInverse(
            -limit, limit, control.rate_limit, control.predictive(), self._phase
        )
        self.shaper = CommandShaper(-limit, limit, control.rate_limit)

    def narrow(self, u: float) -> float:
        """An input as the channel sees it: its part beyond the dead zone."""
        return narrow(u, self.dead_zone)

    def widen(self, v: float) -> float:
        """The input to command for ``v`` beyond the dead zone."""
        return widen(v, self.dead_zone)

    def _fewer_output_lags(
        self,
        options: dict[str, Any],
        model: PredictiveModel,
        record: tuple[list[float], list[float], list[int]],
    ) -> tuple[int, PredictiveModel] | None:
        """The identifier's AR part has an unstable mode (``UNSTABLE_MODE``): the largest
        number of output lags below its own whose identifier, rebuilt from the record, has
        none, and that identifier; None when the AR part has none (or nothing smaller is
        without one).

        An unstable AR part predicts growth with the input held, so its steps never settle,
        the horizon runs to its cap and the horizon test is never passed. On a stable
        plant's noise-free record it is the over-parameterised fit's doing: more output and
        input lags than the plant has can write the same one-step behaviour with a common
        factor in both, and a structural error (a dead zone the cubic map does not hold)
        picks one with an unstable root (docs/control.md, "Fewer output lags where the
        identifier is unstable"). Fewer output lags leave no room for it."""
        if self._output_lags_given:
            return None
        ar = model.dynamics().ar
        if slowest_mode(ar) < UNSTABLE_MODE:
            return None
        for na in range(len(ar) - 1, 0, -1):
            candidate = self._rebuilt({**options, "na": na}, *record)
            if slowest_mode(candidate.dynamics().ar) < UNSTABLE_MODE:
                return na, candidate
        return None

    def _rebuilt(
        self,
        options: dict[str, Any],
        outputs: list[float],
        inputs: list[float],
        runs: list[int],
    ) -> PredictiveModel:
        """A dynamic identifier with ``options`` trained on the horizon test's record in
        order, where the channel trained (a restart's history refilled first)."""
        model = build_model("dynamic", seed=self._seed, **options)
        assert isinstance(model, PredictiveModel)
        history = model.history_length
        for i, (y, u_prev, run) in enumerate(zip(outputs, inputs, runs, strict=True)):
            # As the channel learnt them: every sample while no restart has come since the
            # record began (run == i), then only once a restart's history has refilled.
            if run == i or run > history:
                model.step(u_prev, y)
            else:
                model.observe_only(u_prev, y)
        return model

    def _bridge(self, missing: int, u_now: float) -> bool:
        """Carry the channel across ``missing`` lost samples, when at most ``bridge_gap``
        and the inputs that produced them are known; False to resynchronise instead.

        The first lost output came from ``u_prev``, the input read before the gap; the
        others, and this sample's, from inputs never read. They are taken to be ``u_now``,
        the input read now, when that is either the input read before the gap (nothing
        changed it) or the command this channel last sent (the change is its own, which
        the vehicle applies before its next step as it does every command). Any other
        change happened at an unknown step in the gap: no bridge.

        Each lost step advances every frozen run (the supervisor's, the counterfactual's,
        the multi-step free run) and the controller's internal model on its input, without
        a measurement; the identifier's history and the horizon test's record take the
        model's own prediction in place of the lost output, marked as not measured. So the
        supervisor's windows, the record and the disturbance estimate go on across the gap,
        and the samples whose regressors reach back to an imputed output refill the
        history without training (``refill``), as after a repeat."""
        u_before = self.u_prev
        if (
            not 0 < missing <= self.settings.bridge_gap
            or u_before is None
            or not finite(u_before)
            or self.resync > 0
            or self.last is None
            or not finite(u_now)
        ):
            return False
        if not (self._same_input(u_now, u_before) or self._same_input(u_now, self.last_command)):
            return False
        u = u_before
        for _ in range(missing):
            y_hat = self.model.predict(u)
            self._advance_predictions(math.nan, u, lost=True)
            self.model.observe_only(u, y_hat)
            self.persistence.observe_only(u, y_hat)
            self.horizon_test.record_missing(y_hat, u)
            self.dynamics = self.model.dynamics()
            self.controller.coast(self.dynamics)
            u = u_now
        self.u_prev = u_now  # the input that produced this sample's output
        self.refill = max(self.refill, self.model.history_length)
        self.bridged += missing
        return True

    def _same_input(self, a: float, b: float) -> bool:
        """Two input readings equal to within the wire's resolution, 0.002 of the
        actuator's limit: a command read back from a servo's microseconds (1,100-1,900 µs,
        400 µs a side) is off by up to half of one, 0.00125 of the limit; a float32 by
        far less."""
        return abs(a - b) <= 2e-3 * self.settings.control.u_limit

    def _start_resync(self) -> None:
        """A gap (or the first sample): the history refills without training, and every
        prediction that ran on the history before it restarts."""
        self.resync = self.model.history_length
        self.refill = 0
        self._free_run, self._free_run_left = None, 0
        self._sup_run = None
        self._alt_run = None
        self.controller.reset()
        self.dynamics = None

    def _drop_repeat(self, learnt_last: bool, y: float) -> None:
        """A reading served twice by an asynchronous sampler (a stream at the sample rate,
        with jitter): the previous reading was a step ahead of its tick, so the plant moved
        two steps between it and the one before, and none since. Learning from either pair,
        or from a history holding the wrong step, teaches the model a wrong step response
        (measured on the ArduSub profile: depth error 0.49 m mean over 6 runs with, 0.12 m
        without): the update learnt from the early reading is undone, the repeat dropped
        and the history refilled without training. Control is not interrupted, nor are
        the frozen runs the supervisor and the multi-step accuracy compare with: the
        repeat is the reading of its own tick, so they advance a step on it as on any
        sample (a run that skipped it would lag the plant by a step for each repeat).
        (An exact steady state of a noise-free output also repeats: it holds no new
        information either.)"""
        self.repeats += 1
        if learnt_last:
            self.model.undo_last_update()
        self.refill = self.model.history_length
        self.horizon_test.restart_run()
        assert self.u_prev is not None  # a repeat follows a sample
        self._advance_predictions(y, self.u_prev)

    def _refill_sample(self, y: float, u_now: float) -> None:
        """A sample after a repeat or a reused input: into the history, the horizon test's
        record and the internal model, not into training. The frozen runs go on: they
        run on the inputs alone, which the repeat did not disturb."""
        assert self.u_prev is not None
        self._advance_predictions(y, self.u_prev)
        self.model.observe_only(self.u_prev, y)
        self.persistence.observe_only(self.u_prev, y)
        self.horizon_test.record(y, self.u_prev)
        self.u_prev = u_now
        self.refill -= 1
        self.skipped += 1
        self.dynamics = self.model.dynamics()
        self.controller.track(self.dynamics, y)

    def _resync_sample(self, y: float, u_now: float) -> None:
        """A sample after a gap: into the history only; the horizon test's record breaks
        (consecutive samples only)."""
        self._sup_run = None
        self._alt_run = None
        self.horizon_test.break_record()  # consecutive samples only
        u_guess = u_now if self.u_prev is None else self.u_prev
        self.model.observe_only(u_guess, y)
        self.persistence.observe_only(u_guess, y)
        self.u_prev = u_now
        self.resync -= 1
        self.skipped += 1

    def _advance_predictions(self, y: float, u_prev: float, lost: bool = False) -> None:
        """The frozen copies one step on the input that produced ``y``: the multi-step
        accuracy's free run, the supervisor's prediction and the safe input's
        counterfactual. ``lost``: a bridged step whose output was never read."""
        free_run = self._free_run
        if free_run is not None and (lost or finite(y)):
            y_sim = free_run.advance(u_prev)
            if not lost:
                self.multistep.add(y, y_sim)
        if self._sup_run is not None:
            self._sup_pred = self._sup_run.advance(u_prev)
        if self._alt_run is not None and self._app_run is not None:
            # The counterfactual input reached from the applied one at the rate limit.
            rate = self.settings.control.rate_limit
            target = self._alt_target
            self._alt_u = min(max(target, self._alt_u - rate), self._alt_u + rate)
            neutral = self._alt_run.advance(self._alt_u)
            self._alt_delta = self._app_run.advance(u_prev) - neutral

    def _account(self, estimate: Estimate, y: float, baseline_error: float) -> None:
        """The identifier's step in the health counts and the gates: a rejected sample, a
        divergence (the channel must qualify again), or a sample that counts towards
        convergence and advances the internal model."""
        if estimate.status == "rejected":
            self.rejected += 1
        elif estimate.status == "diverged":
            self.divergences += 1
            self.converged = False
            self.disqualify()
        else:
            self.stats.add(y, estimate.error, baseline_error)
            if not self.converged and self.stats.count >= self.settings.burn_in:
                skill = self.stats.recent_skill()  # only needed until convergence
                if skill is not None and skill >= self.settings.min_skill:
                    self.converged = True
            self.dynamics = self.model.dynamics()
            self._long_run_wait -= 1
            if self._long_run_wait <= 0:
                self._long_run_wait = LONG_RUN_CHECK
                self.controller.reduced = self._contradicted_pairs_removed(self.dynamics)
            self.controller.track(self.dynamics, y)

    def _contradicted_pairs_removed(self, dynamics: ModelDynamics) -> vec[float] | None:
        """G's step response without its near pole–zero pairs (``cancellation.
        reduced_model``) where the record simulated from its inputs fits that input path
        better than G whole (``cancellation.record_prefers``), else None: no such pair, a
        record shorter than the horizon test's window, or a record that keeps them. Asked
        every ``LONG_RUN_CHECK`` samples."""
        control = self.settings.control
        if not control.cancel_near_pairs or self.horizon_test.count < self.horizon_test.window:
            return None
        factors = factorise(dynamics, -control.u_limit, control.u_limit)
        if factors is None:
            return None
        gains, shape = factors
        predictive = self.controller.settings
        reduced = reduced_model(
            dynamics.ar, gains, predictive.band, predictive.min_horizon, predictive.max_horizon
        )
        if reduced is None:
            return None
        outputs, inputs = self.horizon_test.samples()
        mapped = mapped_inputs(shape, inputs)
        full, without = (list(dynamics.ar), gains), (reduced.ar, reduced.gains)
        if not record_prefers(full, without, mapped, outputs):
            return None
        return reduced.response

    def _restart_free_run(self) -> None:
        dynamics = self.model.dynamics()  # a copy of its own: it advances its histories
        horizon = self.controller.horizon_for(dynamics)
        if horizon < 2:
            self._free_run, self._free_run_left = None, self.settings.control.min_horizon
            return
        self._free_run, self._free_run_left = dynamics, horizon

    def blocked_reason(self) -> str:
        if self.resync > 0 or self.last is None:
            return f"identifier resynchronising after a telemetry gap ({self.channel})"
        if self.last.status == "diverged":
            return f"identifier diverged ({self.channel})"
        if not self.converged:
            return (
                f"identifier not converged ({self.channel}: "
                f"{min(self.stats.count, self.settings.burn_in)}/{self.settings.burn_in} samples, "
                f"recent skill {self.stats.recent_skill()})"
            )
        return self._harm_reason()

    def identified(self) -> bool:
        """The identifier's own gate is open: resynchronised, converged, not diverged."""
        return (
            self.resync == 0
            and self.last is not None
            and self.last.status != "diverged"
            and self.converged
        )

    def _harm_reason(self) -> str:
        """The horizon test and the supervisor's verdict (docs/control.md, "Do no harm").

        A tripped channel re-arms once its hold-off has passed and the model passes the
        horizon test on data taken after the trip; an unqualified one qualifies by passing
        it. Once it commands on a verdict covering the whole horizon, the verdict stands
        until a trip, a vehicle restart or a divergence: while the loop holds the output at
        its setpoint there is no change left for the test to judge by, and the supervisor
        watches the loop instead."""
        if (
            self._lags_pending
            and not self._lags_tried
            and not self.active
            and self.horizon_test.count >= LAG_CHOICE_MIN + self._choice_delay
        ):
            # Asked to command: the input lags are chosen now, before the first command,
            # rather than under way.
            self._lags_tried = True
            self._choose_input_lags()
        horizon = self.controller.horizon
        self._asked = True
        if self._slow and self.converged and not self.tripped:
            # The first ask after a stretch on the slow cadence: a verdict on today's model.
            self._evaluate_horizon(on_cadence=False)
        if self.tripped:
            if self.supervisor.latched:
                return (
                    f"supervisor: {self.supervisor.reason}; tripped "
                    f"{self.supervisor.strikes} times, off until control is re-enabled "
                    f"({self.channel})"
                )
            if (
                self._since_trip < self.supervisor.holdoff(horizon)
                or not self._input_moved_since_trip()
                or not self._horizon_passes(horizon)
            ):
                return f"supervisor: {self.supervisor.reason} ({self.channel})"
            self.tripped = False
            self.qualified = self.ever_qualified = True
            self.supervisor.rearms += 1
            self.events.append(self._event("rearm", "", self.supervisor.holdoff(horizon)))
            return ""
        if not self.qualified or not self.horizon_test.full:
            # Until a verdict covers the whole horizon (the record may be shorter at
            # first), the test is re-run every ``refresh`` samples, commanding or not.
            if not self._horizon_passes(horizon):
                self.qualified = False
                return f"model does not predict over the horizon ({self._horizon_verdict()})"
            self.qualified = self.ever_qualified = True
        return ""

    def _input_moved_since_trip(self) -> bool:
        """The record since the input reached its safe input after the trip holds inputs
        that moved by at least ``REARM_INPUT_SPAN`` of the actuator's limit. At a held safe
        input the record shows the output's own dynamics and disturbance and nothing of
        the input's effect, so a model passing the horizon test on it says nothing about
        the response the plan relies on."""
        since = self._since_trip - self._trip_ramp
        span = self.horizon_test.input_span(since)
        return span >= REARM_INPUT_SPAN * self.settings.control.u_limit

    def _horizon_verdict(self) -> str:
        """The horizon test's last figures against what it needs, for ``health``."""
        test = self.horizon_test

        def shown(fit: float | None) -> str:
            return "n/a" if fit is None else f"{fit:.1f} %"

        against_mean = ""
        if test.mean_threshold is not None:
            against_mean = (
                f", {shown(test.mean_fit)} against the mean, needs {test.mean_threshold:g} %"
            )
        return (
            f"{self.channel}: {test.steps}-step fit {shown(test.fit)} of a {test.horizon}-step "
            f"horizon, needs {test.threshold:g} %{against_mean}"
        )

    def _evaluate_horizon(self, on_cadence: bool) -> None:
        """The horizon test on the current model, every ``refresh`` samples (it runs the
        model over the whole record) while its verdict matters: whenever the channel does
        not command (control off, no setpoint, blocked, tripped), and while it commands on
        a verdict from a record shorter than the horizon. The model and its horizon keep
        changing while identification goes on: a verdict from an earlier model, or on a
        shorter horizon, is not one on the model that would command. ``on_cadence``: it
        comes because the wait an earlier one set ran out."""
        refresh = self.settings.control.refresh
        wanted = self._asked or self.tripped or self.active
        self._slow = not wanted
        self._until_evaluation = refresh if wanted else max(refresh, self.settings.window)
        if not on_cadence:
            self._until_evaluation += self._evaluation_offset
        self._on_cadence = True
        self._asked = False
        dynamics = self.dynamics if self.dynamics is not None else self.model.dynamics()
        horizon = self.controller.horizon
        passed = self.horizon_test.evaluate(dynamics, horizon)
        if self.qualified and self.horizon_test.steps < min(horizon, self.horizon_test.minimum):
            # Too short a record since a telemetry gap to judge by: the verdict stands (a
            # gap is not evidence against the model; a trip or a restart clears it).
            return
        self._horizon_ok = passed
        # The verdict qualifies the channel here, on the observing side, whether control is
        # on or not (health's ``horizon_qualified``); a tripped channel re-arms only through
        # ``_harm_reason`` (its hold-off first).
        if not self.tripped:
            self.qualified = passed
            if passed:
                self.ever_qualified = True

    def _horizon_passes(self, horizon: int) -> bool:
        return self._horizon_ok

    def disqualify(self, keep_record: bool = False) -> None:
        """The model must pass the horizon test again: on data taken from now on, or with
        ``keep_record`` on the record as it is (at the next sample)."""
        self.qualified = False
        if not keep_record:
            self.horizon_test.reset()
        self._horizon_ok = False
        self._until_evaluation = 0
        self._on_cadence = False

    def on_restart(self) -> None:
        """The vehicle's clock restarted: stop commanding until the model passes the
        horizon test on data after the restart."""
        self.restarts += 1
        self.disqualify()
        self.deactivate()

    def supervise(self, setpoint: float, u_applied: float) -> str:
        """The supervisor's verdict on this commanded sample ("" or the trip's reason)."""
        if not self.active:
            return ""
        u_applied = self.narrow(u_applied)
        y = self._y_seen
        pred = self._sup_pred
        error = y - setpoint
        if self._sup_run is None or not finite(pred) or setpoint != self._sup_setpoint:
            if setpoint != self._sup_setpoint:
                self.supervisor.new_reference()
                self._restart_comparison(u_applied, setpoint)
            self._restart_supervised(y, setpoint, u_applied)
            return ""
        reason = self.supervisor.segment_sample(
            y, pred, error, pred - setpoint, self._last_saturated
        )
        if not reason and self._alt_run is not None and finite(self._alt_delta):
            # What the output would have been at the neutral input: the measured one
            # (disturbance and noise included) without commanding's modelled effect.
            reason = self.supervisor.compare_sample(
                error,
                error - self._alt_delta,
                "the vehicle's own control" if self.releases else "the neutral input",
            )
        if reason:
            self._trip(reason, u_applied)
            return f"supervisor: {reason} ({self.channel})"
        if self.supervisor.segment_done():
            self._restart_supervised(y, setpoint, u_applied)
        if self._alt_run is None or self.supervisor.comparison_done():
            self._restart_comparison(u_applied, setpoint)
        return ""

    def _restart_comparison(self, u_applied: float, setpoint: float) -> None:
        """The safe input's counterfactual from now: the model from the measured history,
        its input going from the applied one to ``_counterfactual_input`` at the rate
        limit."""
        self._alt_run = self.model.dynamics()
        self._app_run = self.model.dynamics()
        self._alt_u = u_applied if finite(u_applied) else 0.0
        self._alt_target = self._counterfactual_input(self._alt_run, setpoint)
        self.supervisor.start_comparison()

    def _counterfactual_input(self, dyn: ModelDynamics, setpoint: float) -> float:
        """What the channel would get if it stopped commanding: the neutral input (0), or,
        when a trip releases it to the vehicle's own controller, the input that controller
        settles at: the one whose steady state is the setpoint, by the model (0 when the
        model has none)."""
        if not self.releases:
            return 0.0
        limit = self.settings.control.u_limit
        u = steady_input(dyn, setpoint, -limit, limit)
        return u if finite(u) else 0.0

    def _restart_supervised(self, y: float, setpoint: float, u_applied: float) -> None:
        run = self.model.dynamics()
        self._sup_run = run
        self._sup_setpoint = setpoint
        self.supervisor.start_segment(y, y - setpoint, u_applied)
        # The model's steady state at the neutral input (every input lag at 0): what
        # holding trim would give, by the model's own account.
        gain = run.ar_gain()
        if abs(gain) > 1e-9:
            self.supervisor.neutral(run.bias / gain - setpoint)

    def _trip(self, reason: str, u_applied: float) -> None:
        control = self.settings.control
        self.tripped = True
        self._since_trip = 0
        self.disqualify()
        self.deactivate()
        good = self.supervisor.good_u if control.safe_input == "hold" else 0.0  # release: 0
        if not finite(good):
            good = u_applied if finite(u_applied) else 0.0
        limit = control.u_limit - self.dead_zone
        self.safe_u = min(limit, max(-limit, good))
        applied = u_applied if finite(u_applied) else self.safe_u
        travel = abs(applied - self.safe_u) + 2.0 * self.dead_zone
        self._trip_ramp = math.ceil(travel / control.rate_limit) + 2
        self.events.append(self._event("trip", reason))

    @property
    def releases(self) -> bool:
        """A tripped channel sends nothing: its vehicle's own controller takes over."""
        return self.settings.control.safe_input == "release"

    def safe_command(self) -> float:
        """A tripped channel's command: toward its safe input at the rate limit (the
        shaper holds the last command sent), then the safe input itself; NaN (nothing)
        when the safe input is "release"."""
        if self.releases:
            return math.nan
        return self.widen(self.shaper.shape(self.safe_u).u)

    def _event(self, kind: str, reason: str, holdoff: int | None = None) -> dict[str, Any]:
        return {
            "channel": self.channel,
            "event": kind,
            "reason": reason,
            "safe_input": self.widen(self.safe_u) if kind == "trip" and not self.releases else None,
            "safe_mode": self.settings.control.safe_input,
            "trips": self.supervisor.trips,
            "rearms": self.supervisor.rearms,
            "horizon_fit": significant(self.horizon_test.fit),
            "horizon_mean_fit": significant(self.horizon_test.mean_fit),
            "window": self.supervisor.window,
            "horizon": self.controller.horizon,
            "holdoff": holdoff,  # a re-arm: the samples it waited for at least
        }

    def solve(self, setpoint: float, u_applied: float) -> tuple[float, str, bool]:
        """One predictive-inverse step: (command, path, saturated); path is the inverse
        step's ("newton", "fallback") or "hold" when no plan could be made."""
        raw_applied = u_applied
        u_applied = self.narrow(u_applied)
        if not self.active:
            self.probe.stop()
            self.shaper.reset(u_applied)
            # The internal model and its disturbance estimate start with control: what the
            # estimate gathered before, while the model it runs was still being learnt, is
            # model error, not a disturbance (measured on the ArduSub test: d of 0.4-1.6 m
            # at the end of identification in the runs that ended 0.2-0.3 m off).
            self.controller.reset()
            self.active = True
            self.supervisor.arm(
                self.horizon_test.model_rms,
                self.horizon_test.hold_rms,
                self.controller.horizon,
                u_applied,
            )
            self._restart_supervised(self._y_seen, setpoint, u_applied)
        dynamics = self.dynamics if self.dynamics is not None else self.model.dynamics()
        u, path, saturated = self.controller.decide(dynamics, u_applied, setpoint)
        shaped = self.shaper.shape(u)
        self._last_saturated = saturated or shaped.saturated
        command = widen_beside(shaped.u, self.dead_zone, raw_applied, self._crossing_band)
        return command, path, saturated or shaped.saturated or shaped.rate_limited

    def may_probe(self) -> bool:
        """Asked to command, identified, and not qualified by the horizon test: the channel
        probes if its settings allow it (``ControlSettings.probe``). A tripped one first
        waits out its hold-off at the safe input, and does not probe once latched: its
        probe is what lets it re-arm (``_input_moved_since_trip``)."""
        if not self.probe.amplitude > 0.0 or self.qualified:
            return False
        if not self.tripped:
            return True
        holdoff = self.supervisor.holdoff(self.controller.horizon)
        return self._since_trip >= holdoff and not self.supervisor.latched

    def probe_command(self, u_applied: float) -> float:
        """The probing excitation's next input (``umodel.probe``), at the rate limit,
        about the input applied when probing began (kept inside the actuator's range); the
        channel is off its plan meanwhile (``deactivate``), its probe going on."""
        self.deactivate(probing=True)
        u_applied = self.narrow(u_applied)
        if not self.probe.running:
            held = u_applied if finite(u_applied) else 0.0
            limit = self.settings.control.u_limit - self.probe.amplitude
            self.probe.start(min(limit, max(-limit, held)))
            self.shaper.reset(held)
        return self.widen(self.shaper.shape(self.probe.level()).u)

    def deactivate(self, probing: bool = False) -> None:
        """Not commanding from the plan; ``probing``: the channel probes instead, and its
        probe goes on from where it is."""
        if not probing:
            self.probe.stop()
        self.active = False
        self._sup_run = None
        self._alt_run = None
        self.supervisor.disarm()

    def _lag_choice_health(self) -> dict[str, object] | None:
        if self.lag_choice is None:
            return None
        if self._lag_choice_json is None:
            self._lag_choice_json = self.lag_choice.as_json()
        return self._lag_choice_json

    def health(self) -> dict[str, Any]:
        return {
            "model": self._model_name,
            "status": "none" if self.last is None else self.last.status,
            "converged": self.converged,
            "divergences": self.divergences,
            "rejected": self.rejected,
            "skipped": self.skipped,
            "bridged": self.bridged,
            **self.stats.summary(),
            **self.multistep.summary(self.controller.horizon),
            "horizon_fit": significant(self.horizon_test.fit),
            "horizon_mean_fit": significant(self.horizon_test.mean_fit),
            "horizon_samples": self.horizon_test.count,
            "input_lags": self._input_lags,
            "input_dead_zone": self.dead_zone,
            "input_lag_choice": self._lag_choice_health(),
            "horizon_qualified": self.qualified,
            "restarts": self.restarts,
            "supervisor": {
                "state": "tripped" if self.tripped else "armed" if self.active else "idle",
                "trips": self.supervisor.trips,
                "rearms": self.supervisor.rearms,
                "reason": self.supervisor.reason,
                "safe_input": self.widen(self.safe_u)
                if self.tripped and not self.releases
                else None,
                "safe_mode": self.settings.control.safe_input,
            },
        }


class VehiclePipeline:
    def __init__(
        self,
        settings: PipelineSettings | None = None,
        phase: int = 0,
        spread: int = LAG_CHOICE_SPREAD,
    ):
        """``phase``: on which samples the controllers re-derive their plans
        (``PredictiveInverse``) and, modulo ``spread`` (``choice_spread``), how many samples
        late the channels choose their structure; a service gives each vehicle its own."""
        self.settings = settings or PipelineSettings()
        self.channels = {
            ch: ChannelPipeline(ch, self.settings, self.settings.seed * 2 + i, phase, spread)
            for i, ch in enumerate(CHANNELS)
        }
        self.gaps = StepContinuity()

    def observe(
        self, sample: TelemetrySample, inputs_reused: bool = False, sampled: bool = False
    ) -> dict[str, dict[str, Any]]:
        """Estimates per channel (a channel refilling its history after a gap has none).
        ``inputs_reused``: the sample's input readings are the previous sample's (an
        asynchronous sampler knows; see ``ChannelPipeline.observe``)."""
        follows = self.gaps.follows(sample.time_boot_ms)
        missing = self.gaps.missing  # lost just before this sample: a gap to bridge
        if self.gaps.restarted or sample.restarted:  # a periodic source marks a reboot
            follows = False
            missing = 0
            for pipeline in self.channels.values():
                pipeline.on_restart()
        estimates = {}
        for ch, pipeline in self.channels.items():
            estimate = pipeline.observe(
                sample.t,
                sample.output(ch),
                sample.input(ch),
                follows,
                inputs_reused,
                sampled,
                missing,
            )
            if estimate is not None:
                estimates[ch] = estimate
        return estimates

    def decide(
        self, sample: TelemetrySample, setpoints: dict[str, float | None], enabled: bool
    ) -> Decision:
        """The command for this sample, or why there is none."""
        decision = self._decide(sample, setpoints, enabled)
        command = decision.command
        for ch, pipeline in self.channels.items():
            if command is None:
                pipeline.last_command = math.nan
            else:
                sent = command.u_depth if ch == "depth" else command.u_pitch
                pipeline.last_command = pipeline.narrow(sent)
        return decision

    def _decide(
        self, sample: TelemetrySample, setpoints: dict[str, float | None], enabled: bool
    ) -> Decision:
        active = {ch: v for ch, v in setpoints.items() if v is not None and finite(v)}
        if not enabled:
            reason = "control disabled"
            for pipeline in self.channels.values():
                pipeline.supervisor.operator_reset()
        elif not active:
            reason = "no setpoint"
        else:
            reason = ""
        if reason:
            for pipeline in self.channels.values():
                pipeline.deactivate()
            return Decision(None, None, reason)
        # Each channel on its own: a blocked one holds (NaN: the vehicle keeps its input),
        # a tripped one sends its safe input, the others command.
        values = {"depth": math.nan, "pitch": math.nan}
        paths: list[str] = []
        reasons: list[str] = []
        saturated = commanded = False
        for ch, pipeline in self.channels.items():
            if ch not in active:
                pipeline.deactivate()
                paths.append("-")
                continue
            blocked = pipeline.blocked_reason()
            if blocked and not pipeline.identified():
                # The identifier's own gate (resynchronising, diverged, not converged)
                # holds this channel only: a tripped one goes on to its safe input, any
                # other holds its input while the other channel commands.
                pipeline.deactivate()
                if pipeline.tripped and not pipeline.releases:
                    values[ch] = pipeline.safe_command()
                    paths.append("safe")
                    commanded = True
                else:
                    paths.append("-")
                reasons.append(blocked)
                continue
            if not blocked:
                blocked = pipeline.supervise(active[ch], sample.input(ch))
            if pipeline.tripped:
                reasons.append(blocked)
                if pipeline.releases:
                    paths.append("released")
                    continue
                if pipeline.may_probe():
                    values[ch] = pipeline.probe_command(sample.input(ch))
                    paths.append("probe")
                else:
                    values[ch] = pipeline.safe_command()
                    paths.append("safe")
                commanded = True
                continue
            if blocked:
                reasons.append(blocked)
                if pipeline.may_probe():
                    values[ch] = pipeline.probe_command(sample.input(ch))
                    paths.append("probe")
                    commanded = True
                else:
                    pipeline.deactivate()
                    paths.append("-")
                continue
            u, path, sat = pipeline.solve(active[ch], sample.input(ch))
            values[ch] = u
            paths.append(path)
            saturated = saturated or sat
            commanded = True
        reason = "; ".join(reasons)
        if not commanded:
            return Decision(None, None, reason)
        payload = {
            "t": sample.t,
            "u_depth": None if math.isnan(values["depth"]) else values["depth"],
            "u_pitch": None if math.isnan(values["pitch"]) else values["pitch"],
            "setpoints": {ch: setpoints.get(ch) for ch in CHANNELS},
            "saturated": saturated,
            "mode": "/".join(paths),
        }
        return Decision(BallastCommand(values["depth"], values["pitch"]), payload, reason)

    def take_events(self, time_boot_ms: int) -> list[dict[str, Any]]:
        """The supervisors' trips and re-arms since the last call, stamped with the sample."""
        events: list[dict[str, Any]] = []
        for pipeline in self.channels.values():
            for event in pipeline.events:
                events.append({"time_boot_ms": time_boot_ms, **event})
            pipeline.events.clear()
        return events

    def mark_stale(self) -> None:
        for pipeline in self.channels.values():
            pipeline.deactivate()

    def identifier_health(self) -> dict[str, Any]:
        return {ch: pipeline.health() for ch, pipeline in self.channels.items()}

    def configs(self) -> dict[str, dict[str, Any]]:
        return {ch: pipeline.config() for ch, pipeline in self.channels.items()}
