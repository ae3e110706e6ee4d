"""Prometheus metrics of the station: per-stage latency histograms, counts per result code."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from server.store.schemas import MeasurementRecord

# Trigger stages live between 0.1 ms (offset) and the 50 ms deadline; a few buckets past it show
# how late a late trigger was.
STAGE_BUCKETS = (
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.002,
    0.005,
    0.01,
    0.015,
    0.02,
    0.03,
    0.04,
    0.05,
    0.075,
    0.1,
    0.25,
    1.0,
)


class Metrics:
    """One registry per app (tests build many apps; the global registry would collide)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.stage_seconds = Histogram(
            "mvpose_stage_duration_seconds",
            "Duration of each pipeline stage per trigger",
            ["stage"],
            buckets=STAGE_BUCKETS,
            registry=self.registry,
        )
        self.measurements = Counter(
            "mvpose_measurements",
            "Measurements stored, by result and reason code",
            ["result", "reason_code", "reason"],
            registry=self.registry,
        )
        self.chain_head = Gauge(
            "mvpose_chain_head_seq",
            "Sequence number of the newest stored measurement",
            registry=self.registry,
        )

    def observe(self, record: MeasurementRecord, seq: int) -> None:
        for stage, ms in record.timings_ms.items():
            self.stage_seconds.labels(stage=stage).observe(ms / 1e3)
        self.measurements.labels(
            result=record.result, reason_code=str(record.reason_code), reason=record.reason
        ).inc()
        self.chain_head.set(seq)
