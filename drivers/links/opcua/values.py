"""Small conversions between OPC UA values and the station's terms, shared by the link's modules."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

from asyncua import ua

from mvpose_core.reasons import reason_name

from ..base import CalibrationInfo, StoredResult

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


def result_data(r: StoredResult, config_versions: dict[str, int]) -> Any:
    """A stored record as the standard's ResultDataType."""
    processing = None
    if r.total_ms is not None:
        processing = _UA.ProcessingTimesDataType(
            StartTime=r.triggered_at,
            EndTime=r.triggered_at + timedelta(milliseconds=r.total_ms),
            ProcessingDuration=float(r.total_ms))
    return _UA.ResultDataType(
        ResultId=_UA.ResultIdDataType(Id=str(r.result_id)),
        IsPartial=False,
        ResultState=result_state(r.ok, r.reason_code),
        MeasId=_UA.MeasIdDataType(Id=str(r.trigger_id)),
        PartId=_UA.PartIdDataType(Id=r.part_id),
        InternalRecipeId=recipe_id("RecipeIdInternalDataType", r.recipe, r.recipe_version),
        InternalConfigurationId=configuration_id(
            r.calibration_id, r.calibration_sha256,
            config_versions.get(r.calibration_sha256 or "")),
        JobId=_UA.JobIdDataType(Id=str(r.trigger_id)),
        CreationTime=r.triggered_at,
        ProcessingTimes=processing,
        ResultContent=result_content(r.offset, r.sigma_mm, r.sigma_deg) or None)


def when(value: Any) -> datetime:
    if isinstance(value, datetime):
        return value
    if isinstance(value, str):
        try:
            return datetime.fromisoformat(value)
        except ValueError:
            pass
    return datetime.now(UTC)


def result_fields(r: dict[str, Any], configuration: CalibrationInfo | None
                  ) -> tuple[dict[str, ua.Variant], dict[str, ua.Variant]]:
    """One recorded answer (the station's listener dict ``r``) as the result event's fields:
    (mvpose's own, ``ResultManagement/LastResult`` and the event subtype's; ResultReadyEventType's,
    OPC 40100-1 §8.3.8.4, every Mandatory one filled as GetResultById fills it). The record's
    calibration when ``r`` names it, else ``configuration``, the one the station measures with."""
    code = int(r.get("reason_code", 0))
    ok = code == 0 and r.get("result") == "OK"
    at = when(r.get("at"))
    ms = float(r.get("processing_ms") or 0.0)
    offset = [float(x) for x in (r.get("offset") or [])]
    sigma_mm, sigma_deg = float(r.get("sigma_mm") or 0.0), float(r.get("sigma_deg") or 0.0)
    rid, trigger = int(r["result_id"]), int(r.get("trigger_id") or 0)
    own = {
        "ResultNumber": uint32(rid), "TriggerId": uint32(trigger),
        "PartId": ua.Variant(str(r.get("part_id") or ""), ua.VariantType.String),
        "Recipe": ua.Variant(str(r.get("recipe") or ""), ua.VariantType.String),
        "ResultCode": int32(code),
        "Reason": ua.Variant(str(r.get("reason") or reason_name(code)), ua.VariantType.String),
        "ResultMessage": ua.Variant(str(r.get("message") or ""), ua.VariantType.String),
        "Offset": ua.Variant(offset, ua.VariantType.Double),
        "Convention": ua.Variant(str(r.get("convention") or ""), ua.VariantType.String),
        "SigmaTranslationMm": ua.Variant(sigma_mm, ua.VariantType.Double),
        "SigmaRotationDeg": ua.Variant(sigma_deg, ua.VariantType.Double),
        "ProcessingMs": ua.Variant(ms, ua.VariantType.Double),
        "CreationTime": ua.Variant(at, ua.VariantType.DateTime),
    }
    if "calibration_sha256" in r:
        config = configuration_id(r.get("calibration_id"), r.get("calibration_sha256"),
                                  r.get("calibration_version"))
    elif configuration is not None:
        config = configuration_id(configuration.calibration_id, configuration.sha256,
                                  configuration.version)
    else:
        config = configuration_id(None, None, None)

    def struct(value: Any) -> ua.Variant:
        return ua.Variant(value, ua.VariantType.ExtensionObject)

    standard = {
        "ResultId": struct(_UA.ResultIdDataType(Id=str(rid))),
        "IsPartial": boolean(False),
        "ResultState": int32(result_state(ok, code)),
        "MeasId": struct(_UA.MeasIdDataType(Id=str(trigger))),
        "JobId": struct(_UA.JobIdDataType(Id=str(trigger))),
        "PartId": struct(_UA.PartIdDataType(Id=str(r.get("part_id") or ""))),
        "InternalRecipeId": struct(recipe_id("RecipeIdInternalDataType", str(r.get("recipe") or ""),
                                             int(r.get("recipe_version") or 0))),
        "InternalConfigurationId": struct(config),
        "CreationTime": ua.Variant(at, ua.VariantType.DateTime),
        "ProcessingTimes": struct(_UA.ProcessingTimesDataType(
            StartTime=at, EndTime=at + timedelta(milliseconds=ms), ProcessingDuration=ms)),
        "ResultContent": ua.Variant(result_content(offset if ok else None, sigma_mm, sigma_deg),
                                    ua.VariantType.Variant),
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
