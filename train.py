"""Learn the filter's noise parameters, dropout rate and outlier gates against ground truth (Hydra).

    python train.py                      # simulated walks, CPU, about 10 minutes
    python train.py experiment=mistuned  # from every noise parameter 10x off
    tensorboard --logdir outputs/
"""
import hydra
from omegaconf import DictConfig, OmegaConf

from flowins.jobs.cli import user_errors
from flowins.jobs.train import run


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
@user_errors  # a user's mistake: `error: ...`, exit status 2 (HYDRA_FULL_ERROR=1: the traceback)
def main(cfg: DictConfig) -> None:
    run(OmegaConf.to_container(cfg, resolve=True))


if __name__ == "__main__":
    main()
