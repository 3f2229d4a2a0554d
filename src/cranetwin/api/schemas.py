"""Public request and response schemas of the HTTP API (separate from storage models).

All quantities are SI: time [s since the Unix epoch] or ISO 8601 UTC text, lengths [m], angles
[rad], forces [N], torques and moments [N·m], pressures [Pa], masses [kg].
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class Problem(BaseModel):
    """An error (RFC 9457 problem details, media type ``application/problem+json``)."""

    type: str = Field("about:blank", examples=["about:blank"])
    title: str = Field(description="short summary", examples=["Unknown machine"])
    status: int = Field(description="HTTP status code", examples=[404])
    detail: str = Field(description="what was wrong and what was expected",
                        examples=["no machine 'crane-9'; known machines: crane-1"])
    errors: list[dict[str, Any]] | None = Field(
        None, description="validation errors, one per bad field: {loc, msg, type}")


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    version: str = Field(examples=["0.1.0"])


class Location(BaseModel):
    """A GPS position (WGS 84)."""

    lat: float = Field(ge=-90, le=90, description="latitude [deg]", examples=[62.24])
    lon: float = Field(ge=-180, le=180, description="longitude [deg]", examples=[25.75])


class DataRange(BaseModel):
    model_config = ConfigDict(populate_by_name=True)

    from_: str | None = Field(None, alias="from", description="first stored sample (ISO 8601 UTC)",
                              examples=["2026-11-23T06:00:00.000Z"])
    to: str | None = Field(None, description="last stored sample (ISO 8601 UTC)",
                           examples=["2026-11-23T14:00:00.000Z"])


class MachinePublic(BaseModel):
    """A machine as listed on the fleet page."""

    machine_id: str = Field(description="identifier", examples=["crane-1"])
    name: str = Field(description="display name", examples=["Crane 1 (Jyväskylä yard)"])
    model: str = Field(description="machine description name", examples=["patu655"])
    status: Literal["live", "idle", "offline"] = Field(
        description="live: samples within the last few seconds; idle: within the offline "
                    "horizon (CRANETWIN_LIVE_OFFLINE_S, 300 s); offline: older or none")
    last_seen: str | None = Field(description="time of the newest stored sample (ISO 8601 UTC)",
                                  examples=["2026-11-23T10:42:00.000Z"])
    payload_kg: float | None = Field(description="latest payload estimate [kg], null if unknown",
                                     examples=[420.0])
    alarms: int = Field(ge=0, description="events of severity 'critical' in the last 24 h",
                        examples=[0])
    location: Location | None = Field(description="last GPS position, null if unknown")


class MachineDetail(MachinePublic):
    """One machine and the time range of its stored samples."""

    data_range: DataRange


class MachineCreate(BaseModel):
    """Registration of a machine (admin)."""

    model_config = ConfigDict(extra="forbid")

    machine_id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$",
                            description="identifier: letters, digits, '_', '.', '-'",
                            examples=["crane-2"])
    model: str = Field(min_length=1, max_length=64,
                       description="built-in machine description (`cranetwin model list`)",
                       examples=["patu655"])
    name: str | None = Field(None, max_length=200, description="display name (default: the id)")
    wire_id: int | None = Field(None, ge=0, le=2**32 - 1,
                                description="numeric id used on the wire (default: assigned)")
    location: Location | None = None


class MachineCreated(MachineDetail):
    """A registered machine with its HMAC secret, shown only in this response."""

    wire_id: int | None = Field(description="numeric id on the wire", examples=[2])
    secret: str = Field(description="per-machine HMAC key for the sender (hex); shown once")


class MachineUpdate(BaseModel):
    """Metadata changes (admin); omitted fields stay as they are."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(None, min_length=1, max_length=200, examples=["Crane 2 (north)"])
    location: Location | None = None


class SamplesPage(BaseModel):
    """Raw samples of a range, one page."""

    channels: list[str] = Field(description="channel names, column order",
                                examples=[["lift_pA", "lift_pB", "lift_s"]])
    t: list[float] = Field(description="sample times [s since epoch]", examples=[[1795430520.0]])
    values: list[list[float | None]] = Field(
        description="shape (len(t), len(channels)) in channel units (Pa, m, N·m, rad); "
                    "null = missing", examples=[[[1.2e7, 3.0e6, 0.41]]])
    next_cursor: str | None = Field(description="pass as `cursor` for the next page; null = done",
                                    examples=[None])


class PayloadSeries(BaseModel):
    t: list[float] = Field(description="times [s since epoch]")
    kg: list[float | None] = Field(description="payload estimate [kg]")
    std_kg: list[float | None] = Field(description="1-sigma uncertainty of the estimate [kg]")


class ToolForceSeries(BaseModel):
    n: list[list[float | None]] = Field(
        description="estimated force on the tool at the load point, world axes, (n, 3) [N]: "
                    "what the pressures imply beyond gravity, inertia and the payload estimate "
                    "(read the vertical component together with the payload, F_z − max(m, 0)·g); "
                    "null near a singular arm pose")
    sigma_min_m: list[float] = Field(
        description="smallest singular value of the arm's tip-force lever matrix, (n,) [m]")


class ForceObservabilityOut(BaseModel):
    """Whether the pressures resolve one cylinder's force in the replayed window."""

    cylinder: str
    sigma_n: float = Field(description="per-sample force error from the pressure sensors "
                                       "(1σ, unsmoothed) [N]")
    source: str = Field(description="'stated accuracy' (the channels' `accuracy`) or "
                                    "'estimated noise' (from the data)")
    range_n: float = Field(description="range of the replayed force in the window [N]")
    share: float | None = Field(description="sigma_n / range_n (null for a constant force)")
    observable: bool = Field(description="share ≤ 0.1, systematic_share ≤ 0.04 and not flat; "
                                         "false: the force is mostly sensor error, the sensors' "
                                         "stated accuracy alone can put it off by more than the "
                                         "4 % accuracy target, or its pressures never changed")
    systematic_n: float = Field(0.0, description="the systematic floor [N]: what the stated "
                                "accuracy beyond the measured noise (offset, gain) leaves in "
                                "the force after any smoothing (0 without a stated accuracy)")
    systematic_share: float | None = Field(0.0, description="systematic_n / range_n (null for "
                                           "a constant force with a floor)")
    flat: bool = Field(False, description="both chamber pressures read one value throughout "
                       "the window: the sensors show none of the force's variation (a stuck "
                       "sensor or a step coarser than it); the force is then not observable")
    causes: list[Literal["noise share", "systematic floor", "flat pressures"]] = Field(
        default_factory=list, description="why the force is not observable (empty when it is)")


class ModelConsistencyOut(BaseModel):
    """Whether one cylinder's pressures agree with the inverse dynamics of the measured motion
    in the replayed window (docs/ACCURACY.md, 'Model consistency')."""

    cylinder: str
    typical_n: float | None = Field(description="median |1 s mean| of the force residual "
                                                "F − F_id [N]")
    residual_rms_n: float | None = Field(description="RMS of the 1 s means [N]")
    raw_rms_n: float | None = Field(description="RMS of the force residual per sample [N]")
    range_n: float | None = Field(description="range of F_id's 1 s means [N]")
    level_n: float | None = Field(description="RMS of F_id, the force the motion needs [N]")
    share: float | None = Field(description="typical_n / level_n")
    noise_n: float | None = Field(description="what sensor noise leaves in a 1 s mean [N]")
    noise_ratio: float | None = Field(description="typical_n / noise_n")
    consistent: bool = Field(description="false: share > 0.1 and noise_ratio > 3 — the machine "
                                         "file or the mapping does not describe this cylinder")
    c_a: float | None = Field(description="residual's coefficient on A_A·p_A")
    c_b: float | None = Field(description="residual's coefficient on −A_B·p_B")
    r2: float | None = Field(description="share of the residual the pressure fit explains")
    hint: str | None = Field(description="likely cause (swapped chambers) or null")


class TwinOut(BaseModel):
    """Replay of a window (twin output resampled to ``rate_hz``)."""

    t: list[float] = Field(description="time grid [s since epoch], shape (n,)")
    q: list[list[float]] = Field(
        description="joint coordinates, shape (n, 4): slew, lift, jib [rad], extension [m]")
    tip: list[list[float]] = Field(description="load point position in the world, (n, 3) [m]")
    poses: dict[str, list[list[float]]] = Field(
        description="per body: world pose, (n, 16) column-major 4x4 homogeneous matrix [m]")
    cylinder_pins: dict[str, list[list[float]]] = Field(
        description="per cylinder: (n, 6) base pin xyz then rod pin xyz in the world [m]")
    cylinder_forces: dict[str, list[float]] = Field(
        description="per cylinder: rod force (Eq. 1–2, friction included), > 0 pushes [N]")
    utilisation: dict[str, list[float]] = Field(
        description="per cylinder: |force| / force at relief pressure [0..1]")
    joint_torques: list[list[float]] = Field(
        description="inverse-dynamics joint torques/forces, (n, 4) [N·m or N]")
    wrenches: list[list[list[float]]] = Field(
        description="joint reaction wrenches, (n, 4, 6): force xyz [N] then moment xyz [N·m], "
                    "world axes")
    payload: PayloadSeries
    tool_force: ToolForceSeries | None = Field(
        None, description="estimated tool force (excavator digging; any machine whose "
                          "working arm has two or more cylinder joints), else null")
    force_observability: list[ForceObservabilityOut] = Field(
        default_factory=list,
        description="per cylinder: can the pressures resolve its force in the replayed window "
                    "(docs/ACCURACY.md, 'Unobservable forces')")
    model_consistency: list[ModelConsistencyOut] = Field(
        default_factory=list,
        description="per cylinder: do its pressures agree with the motion's inverse dynamics "
                    "beyond sensor noise (docs/ACCURACY.md, 'Model consistency')")


class Series(BaseModel):
    t: list[float] = Field(description="bucket start times [s since epoch]")
    min: list[float | None] = Field(description="minimum per bucket [channel unit]")
    max: list[float | None] = Field(description="maximum per bucket [channel unit]")
    mean: list[float | None] = Field(description="mean per bucket [channel unit]")


class HistoryOut(BaseModel):
    """Load history from the stored summaries, ≤ max_points buckets per channel."""

    channels: dict[str, Series] = Field(
        description="per channel: raw channels (`lift_pA` [Pa]) and derived ones: `force:<cyl>` "
                    "[N], `payload` [kg], `moment:<joint>` [N·m], `working` [0..1]")


class EventOut(BaseModel):
    t: float = Field(description="time of the event [s since epoch]")
    kind: str = Field(examples=["overload"])
    severity: str = Field(examples=["critical"], description="info, warning or critical")
    message: str = Field(examples=["payload 1210 kg above rating 900 kg at 6.1 m reach"])
    evidence: dict[str, Any] = Field(default_factory=dict, description="values behind the event")


class FindOut(BaseModel):
    """When a condition held first (or last) in a range, from the stored summaries."""

    t: float | None = Field(description="start of the first (last) bucket where it held [s], "
                                         "null if never", examples=[1795430520.0])
    value: float | None = Field(description="the bucket's max (op=gt) or min (op=lt) value",
                                examples=[61500.0])


class KeyCreated(BaseModel):
    key_id: str
    role: str
    token: str = Field(description="the key; shown once")
