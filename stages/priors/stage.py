"""The `priors` stage: fit the wheel-vehicle and wheel-wheel mixtures on the train split's true pairs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepword.priors import BicFit, Priors, fit_mixture_bic, log_ratio, make_pair_prior
from deepword.word_format import open_dataset
from stages.priors.pairs import PAIR_TYPES, collect_ratios
from stages.priors.plot import plot_priors


def _subsample(x: np.ndarray, limit: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``limit`` samples (non-pairs outnumber pairs a hundredfold; the fit needs far fewer)."""
    return x if len(x) <= limit else rng.choice(x, size=limit, replace=False)


def run(cfg, inputs: dict[str, Path], out_dir: Path) -> dict[str, float]:
    pcfg, seed = cfg.priors, int(cfg.seed)
    train = open_dataset(inputs["data"]).subset("train")
    ratios = collect_ratios(train)
    rng = np.random.default_rng(seed)
    components = tuple(pcfg.components)

    pair_priors, fits, metrics, summary = {}, {}, {}, {}
    for kind in PAIR_TYPES:
        lab = ratios[kind]
        if len(lab.pairs) < 2:
            raise ValueError(f"priors: the train split has {len(lab.pairs)} true {kind} pairs; need at least 2")
        pos = log_ratio(_subsample(lab.pairs, int(pcfg.max_fit_samples), rng))
        pair_fit: BicFit = fit_mixture_bic(pos, components, seed, int(pcfg.n_init), float(pcfg.reg_covar))
        non_fit = None
        if len(lab.non_pairs) >= 2:
            neg = log_ratio(_subsample(lab.non_pairs, int(pcfg.max_fit_samples), rng))
            non_fit = fit_mixture_bic(neg, components, seed, int(pcfg.n_init), float(pcfg.reg_covar))
        elif pcfg.mode == "posterior":
            raise ValueError(f"priors: posterior mode needs non-pairs, the train split has {len(lab.non_pairs)} {kind}")
        pair_priors[kind] = make_pair_prior(str(pcfg.mode), pair_fit.mixture,
                                            non_fit.mixture if non_fit else None, len(lab.pairs), len(lab.non_pairs))
        fits[kind] = (pair_fit.mixture, non_fit.mixture if non_fit else None)
        metrics[f"priors.{kind}.components"] = float(len(pair_fit.mixture.weights))
        metrics[f"priors.{kind}.log_likelihood"] = pair_fit.log_likelihood
        metrics[f"priors.{kind}.pairs"] = float(len(lab.pairs))
        metrics[f"priors.{kind}.non_pairs"] = float(len(lab.non_pairs))
        if non_fit is not None:
            metrics[f"priors.{kind}.non_pair_components"] = float(len(non_fit.mixture.weights))
            metrics[f"priors.{kind}.non_pair_log_likelihood"] = non_fit.log_likelihood
        summary[kind] = {"bic": {str(k): v for k, v in pair_fit.bic.items()},
                         "non_pair_bic": {str(k): v for k, v in non_fit.bic.items()} if non_fit else None,
                         "n_pairs": int(len(lab.pairs)), "n_non_pairs": int(len(lab.non_pairs))}

    priors = Priors(pair_priors["wheel_vehicle"], pair_priors["wheel_wheel"])
    priors.save(out_dir, extra={"fit": summary, "train_images": len(train)})
    plot_priors(out_dir / "artifacts" / "priors.png", ratios, fits, bins=int(pcfg.plot_bins))
    return metrics
