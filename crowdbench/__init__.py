"""crowdbench: a TorchRL benchmark for robot navigation in human crowds (ETH/UCY replay)."""

__version__ = "0.2.0"
