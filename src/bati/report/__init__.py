"""Tables and figures regenerated from run directories (`bati report DIR`)."""

from bati.report.runs import ReportWarning, RunResult, load_runs

__all__ = ["ReportWarning", "RunResult", "build_report", "load_runs"]


def build_report(*args, **kwargs):
    """See bati.report.build.build_report (imported lazily: it pulls in scipy)."""
    from bati.report.build import build_report as build

    return build(*args, **kwargs)
