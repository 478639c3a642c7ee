"""The training loop's scalar logger (``train.logger``), TorchRL's loggers:

- ``csv``: :class:`~torchrl.record.loggers.csv.CSVLogger`, ``RUN/logs/scalars/<name>.csv`` (``step,value``);
- ``tensorboard``: :class:`~torchrl.record.loggers.tensorboard.TensorboardLogger`, event files in
  ``RUN/tensorboard/`` (needs the ``tensorboard`` package);
- ``wandb``: :class:`~torchrl.record.loggers.wandb.WandbLogger` (needs the ``wandb`` package) *and* the CSV
  files, so that ``crowdbench plot`` and ``resume=true`` work as with ``csv``. The run's files are in
  ``RUN/wandb/``; W&B's own environment variables choose the mode (``WANDB_MODE=offline``: nothing is
  sent, ``wandb sync RUN/wandb/offline-run-*`` uploads later), the project (``WANDB_PROJECT``, default
  ``crowdbench``) and the entity. The run id is kept in ``RUN/wandb/crowdbench-run-id``: ``resume=true``
  continues the same W&B run. The resolved config is the run's W&B config.

The loop calls :func:`close_logger` however training ends (a W&B run is marked failed on an error).
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers.csv import CSVLogger

LOGGERS = ("csv", "tensorboard", "wandb")
WANDB_ID = "crowdbench-run-id"


class TeeLogger:
    """Scalars to several TorchRL loggers (``log_scalar`` only: all the loop uses)."""

    def __init__(self, *loggers):
        self.loggers = loggers

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        for logger in self.loggers:
            logger.log_scalar(name, value, step=step)


def wandb_logger(cfg: DictConfig | None, out_dir: Path, write=print):
    """TorchRL's ``WandbLogger`` for the run in ``out_dir`` (its id kept there: a resumed run continues it)."""
    try:
        import wandb
        from torchrl.record.loggers.wandb import WandbLogger
    except ImportError as e:
        raise ValueError(f"train.logger=wandb needs the wandb package: pip install wandb ({e})") from None
    save_dir = out_dir / "wandb"
    save_dir.mkdir(parents=True, exist_ok=True)
    id_file = save_dir / WANDB_ID
    run_id = id_file.read_text().strip() if id_file.is_file() else secrets.token_hex(4)  # not the run's RNGs
    config = OmegaConf.to_container(cfg, resolve=True) if cfg is not None else None
    logger = WandbLogger(exp_name=out_dir.name, save_dir=str(out_dir), id=run_id,
                         project=os.environ.get("WANDB_PROJECT", "crowdbench"), config=config,
                         log_env_packages=False, settings=wandb.Settings(console="off", silent=True))
    id_file.write_text(run_id + "\n")
    mode = "offline" if logger.experiment.settings.mode in ("offline", "dryrun") else "online"
    url = getattr(logger.experiment, "url", None)
    write(f"wandb: run {run_id} ({mode}) in {save_dir}" + (f", {url}" if url and mode == "online" else ""))
    return logger


def make_logger(kind: str, out_dir: Path, cfg: DictConfig | None = None, write=print):
    """The logger ``train.logger=kind`` names (module docstring); ``ValueError`` naming the missing package."""
    out_dir = Path(out_dir)
    if kind == "csv":
        return CSVLogger(exp_name="logs", log_dir=str(out_dir))
    if kind == "tensorboard":
        from torchrl.record.loggers.tensorboard import TensorboardLogger

        try:
            return TensorboardLogger(exp_name="tensorboard", log_dir=str(out_dir))
        except ImportError as e:
            raise ValueError(f"train.logger=tensorboard needs the tensorboard package ({e})") from None
    if kind == "wandb":
        return TeeLogger(CSVLogger(exp_name="logs", log_dir=str(out_dir)), wandb_logger(cfg, out_dir, write))
    raise ValueError(f"unknown train.logger {kind!r}; valid: {', '.join(LOGGERS)}")


def close_logger(logger, failed: bool = False) -> None:
    """Flush and close ``logger``'s files; end its W&B run (exit code 1 if training ``failed``: then an error
    while closing is ignored, the training error is the one reported)."""
    for lg in getattr(logger, "loggers", (logger,)):
        try:
            finish = getattr(lg.experiment, "finish", None)
            if callable(finish):
                finish(exit_code=1 if failed else 0)
            else:
                lg.shutdown()
        except Exception:
            if not failed:
                raise
