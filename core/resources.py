"""Process resource figures that every platform can give (no bpy, nothing
platform-specific at import time: ``resource`` exists only on POSIX)."""
from __future__ import annotations

import sys


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB; 0.0 where the platform
    gives no figure.  POSIX: ``getrusage`` (kilobytes on Linux, bytes on
    macOS); Windows: ``GetProcessMemoryInfo``'s PeakWorkingSetSize."""
    try:
        if sys.platform == "win32":
            return _windows_peak() / 2 ** 20
        import resource
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / 2 ** 20 if sys.platform == "darwin" else peak / 1024.0
    except Exception:  # a figure for reports only: never fail a render over it
        return 0.0


def _windows_peak() -> int:
    import ctypes
    from ctypes import wintypes

    class Counters(ctypes.Structure):
        _fields_ = [("cb", wintypes.DWORD), ("PageFaultCount", wintypes.DWORD),
                    ("PeakWorkingSetSize", ctypes.c_size_t), ("WorkingSetSize", ctypes.c_size_t),
                    ("QuotaPeakPagedPoolUsage", ctypes.c_size_t), ("QuotaPagedPoolUsage", ctypes.c_size_t),
                    ("QuotaPeakNonPagedPoolUsage", ctypes.c_size_t),
                    ("QuotaNonPagedPoolUsage", ctypes.c_size_t), ("PagefileUsage", ctypes.c_size_t),
                    ("PeakPagefileUsage", ctypes.c_size_t)]

    c = Counters()
    c.cb = ctypes.sizeof(c)
    proc = ctypes.windll.kernel32.GetCurrentProcess()
    if not ctypes.windll.psapi.GetProcessMemoryInfo(proc, ctypes.byref(c), c.cb):
        return 0
    return int(c.PeakWorkingSetSize)
