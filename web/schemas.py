"""Request and response models of the HTTP API (they define the OpenAPI schema at ``/docs``).

All values are in SI units of the channel unless a field says otherwise; ``conventional``
blocks repeat a value in the unit engineers quote (deg/h, deg/sqrt(h), mg, m/s/sqrt(h)).
Numbers that are not finite are sent as ``null``.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator


class ErrorOut(BaseModel):
    chi2_per_dof: float | None = Field(
        None, description="misfit normalised by the estimates' uncertainty (~1 when it fits)")
    max_abs_z: float | None = Field(None, description="largest |z| residual on the Allan curve")
    psd: dict[str, Any] | None = Field(
        None, description="PSD part: Whittle deviance per bin of the measured PSD against the "
                          "estimator's expectation under the model (~1 when it fits), bins, "
                          "share outside the 95 % interval")
    holdout: dict[str, Any] | None = Field(
        None, description="hold-out part (fit reports it; null with a reason here)")
    time_domain: dict[str, Any] | None = Field(
        None, description="time-domain part (fit reports it; null with a reason here)")


class FailureOut(BaseModel):
    tau_s: list[float] = Field(description="[low, high] averaging times in s")
    max_abs_z: float
    direction: str


class ConventionalValueOut(BaseModel):
    value: float
    units: str
    ci95: list[float] | None = None


class TermOut(BaseModel):
    term: str
    params: dict[str, float] = Field(description="parameters in SI units")
    ci95: dict[str, list[float]] = Field(default_factory=dict, description="95 % intervals")
    unresolved: list[str] = Field(default_factory=list, description=(
        "amplitudes whose 95 % interval reaches zero: no estimate, only an upper bound"))
    units: dict[str, str] = Field(default_factory=dict, description="SI units per parameter")
    conventional: dict[str, ConventionalValueOut] = Field(default_factory=dict)
    relative_halfwidth: dict[str, float | None] = Field(
        default_factory=dict, description="(high - low) / (2 value) of the 95 % interval now; "
                                          "null where the interval reaches zero")
    target: dict[str, float] = Field(
        default_factory=dict, description="wanted relative half-width (serve --target)")
    time_to_target_s: dict[str, float | None] = Field(
        default_factory=dict, description="further recording time until the target is met, "
                                          "s (0: met; null: not reachable)")


class ChannelCoefficientsOut(BaseModel):
    channel: str
    units: str
    fs_hz: float
    n_samples: int = Field(description="samples seen")
    duration_s: float = Field(description="record length analysed, gaps excluded, s")
    segments: int
    model_revision: int
    model: list[TermOut]
    error: ErrorOut | None
    failures: list[FailureOut]
    intervals: str | None = Field(
        None, description="how the 95 % intervals were computed: 'profile' (profile "
                          "likelihood, as imunoise fit) or 'jacobian' (linearised, routine "
                          "refits)")
    fitted_samples: int = Field(0, description="samples the published fit rests on")
    fitted_at: float | None = Field(None, description="UNIX time of the published fit, s")


class CoefficientsOut(BaseModel):
    channels: dict[str, ChannelCoefficientsOut]
    samples_seen: int
    record_length_s: float = Field(description="longest channel's analysed length, s")


class OverboundOut(BaseModel):
    """Filter-safe noise model: on or above the measured upper 95 % bound at every tau."""

    model_adev: list[float | None]
    N: float = Field(description="white-noise density, units/sqrt(Hz)")
    K: float = Field(description="random-walk density, units/sqrt(s)")
    markov: list[dict[str, float]] = Field(description="first-order Markov states: sigma, T_s")
    median_excess: float = Field(description="median of model/upper - 1 over the taus")
    max_excess: float


class AllanOut(BaseModel):
    channel: str
    units: str
    tau_s: list[float | None]
    adev: list[float | None]
    ci_low: list[float | None] = Field(description="95 % band of the Allan deviation")
    ci_high: list[float | None]
    model: list[str]
    model_adev: list[float | None] | None
    terms: dict[str, list[float | None]] = Field(description="each term's Allan deviation")
    z: list[float | None] | None = Field(description="standardised residual at each tau")
    failures: list[FailureOut]
    error: ErrorOut | None
    overbound: OverboundOut | None = Field(
        None, description="over-bounding model for a Kalman filter (after the first fit)")


class PsdOut(BaseModel):
    channel: str
    units: str
    f_hz: list[float | None]
    psd: list[float | None] = Field(description="one-sided PSD")
    ci_low: list[float | None]
    ci_high: list[float | None]
    dof: list[float | None]
    model_psd: list[float | None] | None = Field(
        description="the estimator's expected value under the fitted model")
    z: list[float | None] | None = Field(
        None, description="normal score of each point under its chi-square law")


class ApplyOut(BaseModel):
    """How to apply a suggestion: the full model specification and extra command-line
    options of ``imunoise fit``/``diagnose`` (empty when the remedy is a term)."""

    model: str
    args: list[str] = Field(default_factory=list)


class SuggestionOut(BaseModel):
    term: str
    action: str = Field("add", description=(
        "add the term, cut the record (apply.args), or remove a term of the model whose "
        "amplitude the record does not resolve"))
    label: str = Field("", description="the removed term's label (name#K when repeated)")
    params: dict[str, float | None]
    ci95: dict[str, list[float | None]] = Field(default_factory=dict)
    unresolved: list[str] = Field(default_factory=list, description=(
        "amplitudes whose 95 % interval reaches zero: no estimate, only an upper bound"))
    chi2_per_dof_before: float | None = None
    chi2_per_dof_after: float | None
    significant: bool
    p_value: float | None = Field(None, description="corrected for the number of candidates")
    why: str
    evidence: list[str] = Field(default_factory=list)
    apply: ApplyOut | None = Field(None, description="how to apply it: POST /model {model}")


class FindingOut(BaseModel):
    kind: str
    p_value: float
    why: str
    range: dict[str, list[float]] = Field(default_factory=dict)


class DiagnosisOut(BaseModel):
    channel: str
    model: list[str]
    note: str = Field("", description="why there are no suggestions yet, if so")
    model_revision: int
    error: ErrorOut | None
    suggestions: list[SuggestionOut]
    findings: list[FindingOut] = Field(
        default_factory=list, description="outliers, gaps, a changing noise level: why a "
                                          "model can look wrong without a missing term")


class HistoryPointOut(BaseModel):
    revision: int
    model: list[str]
    chi2_per_dof: float | None = Field(description="null when the fit's misfit is not finite")
    psd_deviance_per_bin: float | None = Field(
        None, description="the PSD part: Whittle deviance per bin of the streaming PSD under "
        "the fit (computed once per history interval and model); null before a PSD estimate")
    time_s: float = Field(description="UNIX time, s")
    n_samples: int


class ModelOut(BaseModel):
    channel: str
    model: list[str]
    model_revision: int
    valid_terms: list[str]
    error: ErrorOut | None
    history: list[HistoryPointOut]


class ModelChangeRequest(BaseModel):
    """Add or remove one term, or replace the whole model by a list of terms or by a model
    specification (a suggestion's ``apply.model``); exactly one of the four."""

    model_config = ConfigDict(extra="forbid")
    channel: str
    add: str | None = None
    remove: str | None = None
    terms: list[str] | None = None
    model: str | None = None

    @model_validator(mode="after")
    def _one_action(self) -> ModelChangeRequest:
        given = [k for k in ("add", "remove", "terms", "model") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of 'add', 'remove', 'terms' or 'model'")
        return self


class RefitRequest(BaseModel):
    """Refit one channel now (``profile``: cold start and profile intervals, as imunoise fit)."""

    model_config = ConfigDict(extra="forbid")
    channel: str
    intervals: str = Field("profile", pattern="^(profile|jacobian)$")


class ModelChangeOut(BaseModel):
    channel: str
    model: list[str]
    model_revision: int
    error_before: ErrorOut
    error_after: ErrorOut


class HealthOut(BaseModel):
    status: str
    uptime_s: float
    acquiring: bool
    device: dict[str, Any]
    samples: dict[str, int] = Field(description="received, analysed, not_analysed, dropped")
    gaps: int
    last_block_age_s: float | None
    losses: dict[str, int] = Field(
        default_factory=dict,
        description="samples lost by stage: 'device' (FIFO overrun, data-ready missed, reads "
                    "too late: gaps in the recording), 'handover' (not passed from the "
                    "acquisition process to the analysis: the recording has them), 'analysis' "
                    "(not analysed: queue full)")
    acquisition_process: dict[str, Any] | None = Field(
        None, description="the acquisition process: pid, alive, restarts, last_exit, priority "
                          "(policy granted and what was refused), kernel_workers (when "
                          "serve raises the kernel's unbound workers, by default for the "
                          "ADIS16350: policy, threads holding it, holders: serve processes "
                          "sharing them, refused), "
                          "simulator (for "
                          "sim:adis16350: its pid and samples_never_read, the simulated "
                          "part's own count of samples lost at the device); null when "
                          "acquiring in-process")
    recording: dict[str, Any]
    channels: list[str]
    devices: list[dict[str, Any]] | None = Field(
        None, description="several devices at once (serve --device A --device B): each one's "
                          "name (its topic name, /NAME/imu), spec, state, samples, gaps, "
                          "reconnects, last_error, losses by stage as in 'losses', and its "
                          "channels (TOPIC:gyro_x); null for a single device")
    analysis: dict[str, Any] | None = Field(
        None, description="fit scheduler: CPU budget and use, median CPU s per job kind, "
                          "refit period per channel")
    error: str | None
