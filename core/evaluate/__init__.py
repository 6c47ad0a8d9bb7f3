"""Metrics against ground truth (usually a simulated block's ``truth/`` folder, see ``simulate.truth``), used by
tests, benchmarks and reports: orientation (:mod:`.orientation`), rasters (:mod:`.rasters`), and one module per
stage for its own figures."""
