"""crowdbench: a TorchRL benchmark for robot navigation in human crowds (ETH/UCY replay)."""

__version__ = "0.2.0"

import warnings

# ./configs/ (hydra.searchpath of crowdbench/conf/config.yaml) is optional: a directory without it is the
# common case, not worth Hydra's warning on every command
warnings.filterwarnings("ignore", message=r"provider=hydra\.searchpath in main, path=configs is not available")
