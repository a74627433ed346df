"""Metric-test fixtures: the graph tests' demo graph (generated bars, built small)."""

from tests.graph.conftest import demo_bars, demo_build, demo_graph  # noqa: F401
