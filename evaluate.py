"""Evaluate the fusion combinations of the paper's Table I on a sequence (Hydra).

    python evaluate.py                 # simulated 300 s walk, filter + smoother RMSE
    python evaluate.py quick=true      # 60 s version
"""
import hydra
from omegaconf import DictConfig, OmegaConf

from flowins.jobs.cli import user_errors
from flowins.jobs.evaluate import run


@hydra.main(version_base="1.3", config_path="configs", config_name="evaluate")
@user_errors  # a user's mistake: `error: ...`, exit status 2 (HYDRA_FULL_ERROR=1: the traceback)
def main(cfg: DictConfig) -> None:
    run(OmegaConf.to_container(cfg, resolve=True))


if __name__ == "__main__":
    main()
