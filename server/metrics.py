"""Prometheus metrics of the station: per-stage latency histograms, counts per result code.

The station process counts (it appends the records); the API process serves the scrape. The API
asks the station for its exposition text over the control channel at each scrape and serves it
with its own families that the station does not have (:func:`scrape`), so nothing is added to
the trigger path and the same works when the two run in containers of their own.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.metrics_core import GaugeMetricFamily, Metric
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.registry import Collector

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


def exposition(metrics: Metrics) -> str:
    """The registry's Prometheus text: what the station answers the control channel's
    ``metrics`` operation with."""
    return generate_latest(metrics.registry).decode()


class _Families(Collector):
    def __init__(self, families: Iterable[Metric]) -> None:
        self.families = list(families)

    def collect(self) -> Iterator[Metric]:
        return iter(self.families)


def scrape(own: CollectorRegistry, station_text: str | None, with_station: bool) -> bytes:
    """The API's scrape: the station process's families (``station_text``; None when it did not
    answer), then the API's own families that the station does not have (its chain head, read
    at start-up, is the station's when the station answers). With a station process
    (``with_station``), ``mvpose_station_up`` says whether its metrics are in the scrape.

    ValueError when ``station_text`` is not Prometheus text."""
    station = list(text_string_to_metric_families(station_text)) if station_text else []
    names = {f.name for f in station}
    families = station + [f for f in own.collect() if f.name not in names]
    if with_station:
        families.append(GaugeMetricFamily(
            "mvpose_station_up", "1 when the station process answered this scrape with its "
            "metrics, 0 when it did not (its counters are then missing)",
            value=1.0 if station_text else 0.0))
    registry = CollectorRegistry(auto_describe=False)
    registry.register(_Families(families))
    return generate_latest(registry)
