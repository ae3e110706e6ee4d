"""Gauge capability studies of the station: data selection, the stored study, its report."""
