"""A process's own resident memory and its peak (Linux /proc), for the export benchmarks."""

from __future__ import annotations


def rss_mb(field: str) -> float:
    """Resident memory now (VmRSS) or at its peak since the last reset (VmHWM), in MB."""
    with open("/proc/self/status") as status:
        line = next(line for line in status if line.startswith(field + ":"))
    return int(line.split()[1]) / 1024


def reset_peak() -> None:
    """Start the peak (VmHWM) afresh, so it is what comes next (Linux 4.0+: clear_refs 5)."""
    with open("/proc/self/clear_refs", "w") as refs:
        refs.write("5")
