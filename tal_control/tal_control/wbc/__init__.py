"""Whole-body controllers: the passive sWBC (rigid contacts) and, later, the c3WBC (compliant contacts)."""

from .swbc import StandardWbc, WbcSettings, WbcSolution
from .tasks import WbcGains, WbcReferences

__all__ = ["StandardWbc", "WbcGains", "WbcReferences", "WbcSettings", "WbcSolution"]
