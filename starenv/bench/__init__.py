"""The scenario benchmark runner: bench files (``spec``), resumable local / Ray execution (``runner``), reports
(``report``).  ``starenv bench BENCH.toml --out DIR`` drives all three."""

from starenv.bench.report import write_report
from starenv.bench.runner import comparable, read_run, run_bench
from starenv.bench.spec import BenchError, load_bench, parse_bench

__all__ = ["BenchError", "comparable", "load_bench", "parse_bench", "read_run", "run_bench", "write_report"]
