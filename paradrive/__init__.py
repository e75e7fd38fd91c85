"""ParaDrive builder: parallel-trajectory video pairs from single-pass driving logs."""

__version__ = "0.1.0"
