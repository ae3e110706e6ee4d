"""Small conversions between OPC UA values and the station's terms, shared by the link's modules."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from asyncua import ua

from mvpose_core.reasons import reason_name

from ..base import CalibrationInfo
from ..result import ResultEvent

_UA: Any = ua  # the NodeSet's structures are made at import time; asyncua's stubs are strict
RESULT_STATE_COMPLETED = 1  # ResultStateDataType (OPC 40100-1 §12.19): processing completed
RESULT_STATE_FAILED = 4  # failed; as a filter value: every not-OK result
NO_HANDLE = 0  # mvpose hands out no handles: every query's data is in its answer


def arg(name: str, datatype: int, rank: int = -1) -> ua.Argument:
    out = ua.Argument()
    out.Name = name
    out.DataType = _UA.NodeId(datatype)
    out.ValueRank = rank
    out.Description = ua.LocalizedText(name)
    return out


def typedef(nodeid: ua.NodeId | None) -> ua.NodeId:
    if nodeid is None:
        raise RuntimeError("an instance of the Machine Vision model has no type definition")
    return nodeid


def int32(value: int) -> ua.Variant:
    return ua.Variant(int(value), ua.VariantType.Int32)


def uint32(value: int) -> ua.Variant:
    return ua.Variant(int(value), ua.VariantType.UInt32)


def boolean(value: bool) -> ua.Variant:
    return ua.Variant(bool(value), ua.VariantType.Boolean)


def struct_id(value: Any) -> str:
    """The Id field of an OPC 40100 id structure (MeasId, PartId, RecipeId ...), or ''."""
    got = getattr(value, "Id", None)
    if got is None and isinstance(value, str):
        got = value
    return str(got or "").strip()


def struct_version(value: Any) -> str:
    """The Version field of a RecipeId or ConfigurationId structure, or ''."""
    return str(getattr(value, "Version", None) or "").strip()


def recipe_id(cls: str, name: str, version: int, sha256: str = "",
              number: int = 0) -> Any:
    """A RecipeIdInternalDataType (``cls``): Id = recipe name, Version = the store's version,
    Hash = the content's sha256, Description = the number controllers select it by."""
    return getattr(_UA, cls)(
        Id=name, Version=str(version) if version else None,
        Hash=bytes.fromhex(sha256) if sha256 else None,
        HashAlgorithm="SHA-256" if sha256 else None,
        Description=ua.LocalizedText(f"recipe number {number}") if number else None)


def configuration_id(calibration_id: str | None, sha256: str | None,
                     version: int | None) -> Any:
    """A ConfigurationIdDataType: Id = the calibration file's id, Version = the store's version,
    Hash = the calibration's sha256."""
    return _UA.ConfigurationIdDataType(
        Id=calibration_id or "", Version=str(version) if version else None,
        Hash=bytes.fromhex(sha256) if sha256 else None,
        HashAlgorithm="SHA-256" if sha256 else None)


def configuration(c: CalibrationInfo) -> Any:
    return _UA.ConfigurationDataType(
        InternalId=configuration_id(c.calibration_id, c.sha256, c.version),
        LastModified=c.created_at)


def result_state(ok: bool, reason_code: int) -> int:
    """1 (Completed) for an OK result; a not-OK one: minus its reason code (values below 0 are
    the system's own in OPC 40100-1)."""
    return RESULT_STATE_COMPLETED if ok else -abs(int(reason_code) or RESULT_STATE_FAILED)


def result_content(offset: Any, sigma_mm: float, sigma_deg: float) -> list[ua.Variant]:
    """ResultContent: the offset (6 Doubles, recipe convention) and 1σ in mm and degrees: 8
    Doubles; empty unless the result is OK."""
    if not offset:
        return []
    return [ua.Variant(float(v), ua.VariantType.Double)
            for v in (*offset, sigma_mm, sigma_deg)]


def result_data(r: ResultEvent, config_versions: dict[str, int]) -> Any:
    """A stored record's event as the standard's ResultDataType."""
    processing = None
    if r.processing_ms is not None:
        processing = _UA.ProcessingTimesDataType(
            StartTime=r.triggered_at,
            EndTime=r.triggered_at + timedelta(milliseconds=r.processing_ms),
            ProcessingDuration=float(r.processing_ms))
    return _UA.ResultDataType(
        ResultId=_UA.ResultIdDataType(Id=str(r.result_id)),
        IsPartial=False,
        ResultState=result_state(r.ok, r.reason_code),
        MeasId=_UA.MeasIdDataType(Id=str(r.trigger_id)),
        PartId=_UA.PartIdDataType(Id=r.part_id or ""),
        InternalRecipeId=recipe_id("RecipeIdInternalDataType", r.recipe, r.recipe_version),
        InternalConfigurationId=configuration_id(
            r.calibration_id, r.calibration_sha256,
            config_versions.get(r.calibration_sha256 or "")),
        JobId=_UA.JobIdDataType(Id=str(r.trigger_id)),
        CreationTime=r.triggered_at,
        ProcessingTimes=processing,
        ResultContent=result_content(r.robot_offset, r.sigma_mm or 0.0, r.sigma_deg or 0.0)
        or None)


_VARIANTS: dict[type, tuple[Any, ua.VariantType]] = {
    bool: (False, ua.VariantType.Boolean), int: (0, ua.VariantType.Int64),
    float: (0.0, ua.VariantType.Double), str: ("", ua.VariantType.String),
}


def shown_fields() -> list[tuple[str, str, Any, ua.VariantType]]:
    """The result event's SHOWN fields as LastResult variables and event properties: (node
    name in CamelCase, field name, value when the event has none, variant type)."""
    out = []
    for name, tp in ResultEvent.shown():
        if tp not in _VARIANTS:
            raise TypeError(f"result event field {name!r}: no OPC UA type for {tp!r}")
        default, vt = _VARIANTS[tp]
        out.append(("".join(p.title() for p in name.split("_")), name, default, vt))
    return out


def result_fields(r: ResultEvent, config_versions: dict[str, int]
                  ) -> tuple[dict[str, ua.Variant], dict[str, ua.Variant]]:
    """One recorded answer as the result event's fields: (mvpose's own, which are also
    ``ResultManagement/LastResult``; ResultReadyEventType's, OPC 40100-1 §8.3.8.4, every
    Mandatory one as GetResultById has it: taken from :func:`result_data`)."""
    own = {
        "ResultNumber": uint32(r.result_id), "TriggerId": uint32(r.trigger_id),
        "PartId": ua.Variant(r.part_id or "", ua.VariantType.String),
        "Recipe": ua.Variant(r.recipe, ua.VariantType.String),
        "ResultCode": int32(r.reason_code),
        "Reason": ua.Variant(r.reason or reason_name(r.reason_code), ua.VariantType.String),
        "ResultMessage": ua.Variant(r.message, ua.VariantType.String),
        "Offset": ua.Variant([float(x) for x in (r.robot_offset or ())], ua.VariantType.Double),
        "Convention": ua.Variant(r.convention or "", ua.VariantType.String),
        "SigmaTranslationMm": ua.Variant(r.sigma_mm or 0.0, ua.VariantType.Double),
        "SigmaRotationDeg": ua.Variant(r.sigma_deg or 0.0, ua.VariantType.Double),
        "ProcessingMs": ua.Variant(r.processing_ms or 0.0, ua.VariantType.Double),
        "CreationTime": ua.Variant(r.triggered_at, ua.VariantType.DateTime),
        **{node: ua.Variant(getattr(r, name) if getattr(r, name) is not None else default, vt)
           for node, name, default, vt in shown_fields()},
    }
    d = result_data(r, config_versions)

    def struct(value: Any) -> ua.Variant:
        return ua.Variant(value, ua.VariantType.ExtensionObject)

    standard = {
        "ResultId": struct(d.ResultId), "IsPartial": boolean(d.IsPartial),
        "ResultState": int32(d.ResultState), "MeasId": struct(d.MeasId),
        "JobId": struct(d.JobId), "PartId": struct(d.PartId),
        "InternalRecipeId": struct(d.InternalRecipeId),
        "InternalConfigurationId": struct(d.InternalConfigurationId),
        "CreationTime": ua.Variant(d.CreationTime, ua.VariantType.DateTime),
        "ProcessingTimes": struct(d.ProcessingTimes or _UA.ProcessingTimesDataType(
            StartTime=d.CreationTime, EndTime=d.CreationTime)),
        "ResultContent": ua.Variant(d.ResultContent or [], ua.VariantType.Variant),
    }
    return own, standard


# SystemStateDataType (OPC 40100-1 §12.21, the SEMI E10 states): PRD_1 production, a job runs;
# SBY_2 stand-by, ready for a command; SDT_4 scheduled downtime (halted on request). The
# automatic mode's states, and Halted, as the link shows them (.link: _show_states).
SYSTEM_STATES = {"SingleExecution": 1, "ContinuousExecution": 1, "Ready": 2, "Initialized": 2}
SYSTEM_STATE_HALTED = 4


def system_state(state: str, auto_state: str) -> Any:
    """VisionSystem/SystemState (SystemStateDescriptionDataType) for the VisionStateMachine's
    ``state`` and the automatic mode's ``auto_state``."""
    code = SYSTEM_STATES.get(auto_state, 2) if state == "Operational" else SYSTEM_STATE_HALTED
    return _UA.SystemStateDescriptionDataType(State=_UA.SystemStateDataType(code))
