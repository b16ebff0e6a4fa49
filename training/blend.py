"""The blended regression (``blend='auto'`` with an LSTM, ``'on'`` also with an F-RNN or
SF-RNN): solve the :class:`~tactile.training.model.WindowRegression` and choose its weight
beside the recurrent model on the validation windows.

On recordings that drift over time (a BioTac's later repetitions) an LSTM trained by
mini-batch Adam extrapolates worse than a logistic regression on whole-window features solved
to its optimum, while the LSTM leads on data close in time to its training; their
log-probabilities mixed do better than either on the validation windows and carry further
(``docs/results.md``, "The blended regression"). :func:`choose` runs after the first
training: ``C`` of the regression from :data:`CS` on its own validation accuracy, then the
weight from :data:`WEIGHTS` on the mixed model's; :func:`refit` solves the regression again
on training + validation windows with the chosen ``C``. The solver is scikit-learn's (in the
``train`` extra), so the regression is the bench's baseline, fitted on the model's features.
"""

from __future__ import annotations

import copy
import warnings

import numpy as np
import torch

from tactile.errors import ConfigError
from tactile.training.evaluate import predict

CS = (0.01, 0.1, 1.0, 10.0)
"""Inverse L2 strengths tried (scikit-learn's ``C``, ``bench/baselines.py``'s grid); ties: the
smaller."""
WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)
"""The regression's weights tried; ties: the smaller (0: the LSTM alone)."""
NAMES = {"lstm": "LSTM", "f_rnn": "F-RNN", "sf_rnn": "SF-RNN"}
"""The recurrent model of each model that blends, as the log names it."""
ABSENT = -1e4
"""The intercept of a class no training window has (its probability 0 in float32)."""


def solve(x: np.ndarray, y: np.ndarray, n_classes: int, c: float,
          start: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """scikit-learn's multinomial logistic regression (L-BFGS, L2, ``C = c``, as
    ``bench/baselines.py`` fits it) on standardised features ``x`` (N, F), labels ``y``:
    (coef (F, classes), intercept (classes,)) float64, the logits of every class (one absent
    from ``y`` gets :data:`ABSENT`). ``start``: a solution to go on from (warm start).
    One BLAS thread: more spin on a busy machine (the bench measured 20 s against 5 min)."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.linear_model import LogisticRegression
    from threadpoolctl import threadpool_limits

    present = np.unique(y)
    coef = np.zeros((x.shape[1], n_classes))
    intercept = np.full(n_classes, ABSENT)
    if len(present) == 1:
        intercept[present[0]] = 0.0
        return coef, intercept
    lr = LogisticRegression(C=c, max_iter=MAX_ITERATIONS, warm_start=start is not None)
    binary = len(present) == 2
    if start is not None:  # scikit-learn's layout: (1 or classes present, F)
        w0, b0 = start[0][:, present].T, start[1][present]
        lr.coef_, lr.intercept_ = ((w0[1:] - w0[:1], b0[1:] - b0[:1]) if binary else (w0, b0))
    with threadpool_limits(1), warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        lr.fit(x, y)
    w, b = lr.coef_, lr.intercept_
    if binary:  # one logit: the second class's against the first's
        w, b = np.concatenate([np.zeros_like(w), w]), np.concatenate([[0.0], b])
    coef[:, present], intercept[present] = w.T, b
    return coef, intercept


MAX_ITERATIONS = 2000


def _features(regression, f: torch.Tensor, batch: int = 2048) -> torch.Tensor:
    """(N, T, F) windows' features -> (N, F') the regression's, float64 on the CPU."""
    dev = regression.coef.device
    with torch.no_grad():
        return torch.cat([regression.features(f[i : i + batch].to(dev)).cpu()
                          for i in range(0, len(f), batch)]).double()


def fit(regression, x: np.ndarray, y: np.ndarray, c: float, warm: bool = False,
        left_out: np.ndarray | None = None) -> None:
    """Set ``regression``'s standardisation from the windows' features ``x`` (N, F; its
    ``features``) and its weights to the solution for ``c`` on them (``warm``: going on from
    its weights). ``left_out``: features to leave out (a centred channel's mean: always 0 but
    for rounding); so is any that does not vary."""
    mean, std = x.mean(axis=0), x.std(axis=0)
    scale = np.where(std > 1e-6, 1.0 / np.maximum(std, 1e-6), 0.0)
    if left_out is not None:
        mean[left_out], scale[left_out] = 0.0, 0.0
    start = None
    if warm:
        start = (regression.coef.double().cpu().numpy(),
                 regression.intercept.double().cpu().numpy())
    coef, intercept = solve((x - mean) * scale, y, regression.coef.shape[1], c, start)
    for name, value in (("feature_mean", mean), ("feature_scale", scale), ("coef", coef),
                        ("intercept", intercept)):
        getattr(regression, name).copy_(torch.from_numpy(value).float())


def _log_probs(regression, f: torch.Tensor) -> np.ndarray:
    """The regression alone's log-probabilities of the windows' features ``f`` (N, T, F)."""
    regression.eval()
    with torch.no_grad():
        logits = torch.cat([regression(f[i : i + 2048].to(regression.coef.device)).cpu()
                            for i in range(0, len(f), 2048)])
        return torch.log_softmax(logits.double(), dim=1).numpy()


def _figures(log_p: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(accuracy, mean cross-entropy) of the log-probabilities ``log_p`` (N, classes)."""
    lp = log_p - np.logaddexp.reduce(log_p, axis=1, keepdims=True)
    return float((lp.argmax(1) == y).mean()), float(-lp[np.arange(len(y)), y].mean())


def _left_out(model) -> np.ndarray:
    """The regression's features to leave out: the means of the channels centred on their own
    (0 in every window; a signal centred whole keeps each sub-sample's; a granular model's
    preprocessing centres none)."""
    mask = getattr(model.pre, "centred_alone", None)
    return np.flatnonzero(mask.cpu().numpy()) if mask is not None else np.zeros(0, np.int64)


def weights(model) -> tuple[float, ...]:
    """The mixes tried: :data:`WEIGHTS`; with ``state='carry'`` not 1, which would leave the
    carried state nothing to do."""
    return WEIGHTS[:-1] if model.cfg.state == "carry" else WEIGHTS


def choose(model, parts: dict, feats: dict, dist, check=lambda: None) -> dict:
    """After the first training (its best weights in ``model``, a :class:`Blend` head whose
    mix is still 0): ``C`` on the regression's validation accuracy, the regression solved on
    the training windows, then the mix on the validation accuracy of the model as it will be
    (``predict`` at each mix; a lower validation loss, as training's validation measures it,
    breaking ties). ``check()`` between the fits (it raises to stop). Rank 0's result is every
    process's. Returns the choice and its validation figures, for the run's history."""
    head, reg = model.head, model.head.regression
    y_tr, y_val = parts["train"].y, parts["val"].y
    x_tr, x_val = _features(reg, feats["train"]).numpy(), feats["val"]
    left_out = _left_out(model)
    val_acc, solutions = {}, {}
    for i, c in enumerate(CS):  # ascending C, each going on from the last
        check()
        fit(reg, x_tr, y_tr, c, warm=i > 0, left_out=left_out)
        solutions[c] = copy.deepcopy(reg.state_dict())
        val_acc[c] = _figures(_log_probs(reg, x_val), y_val)[0]
    best_c = max(CS, key=lambda c: (val_acc[c], -c))
    reg.load_state_dict(solutions[best_c])
    mixed = {}
    for w in weights(model):
        check()
        head.mix.fill_(w)
        probs = predict(model, parts["val"], feats=feats["val"]).astype(np.float64)
        mixed[w] = _figures(np.log(probs + 1e-9), y_val)
    best_w = WEIGHTS[0]
    for w in list(mixed)[1:]:  # more accurate, or as accurate with a lower loss (by > 1e-9)
        (acc, loss), (best_acc, best_loss) = mixed[w], mixed[best_w]
        if acc > best_acc + 1e-12 or (abs(acc - best_acc) <= 1e-12 and loss < best_loss - 1e-9):
            best_w = w
    head.mix.fill_(best_w)
    dist.sync_buffers(head)  # (each process solved alike; rank 0's is kept)
    return {"c": best_c, "mix": best_w, "val_acc": mixed[best_w][0],
            "regression_val_acc": val_acc[best_c], "recurrent_val_acc": mixed[0.0][0]}


def refit(model, w, f: torch.Tensor, choice: dict, dist) -> None:
    """The regression solved again on the windows ``w`` (features ``f``: training +
    validation) with the chosen ``C``; the chosen mix set."""
    head = model.head
    fit(head.regression, _features(head.regression, f).numpy(), w.y, float(choice["c"]),
        warm=True, left_out=_left_out(model))
    head.mix.fill_(float(choice["mix"]))
    dist.sync_buffers(head)


def check_available(setting: str = "auto") -> None:
    """scikit-learn (the solver) importable, else a one-line :class:`ConfigError` naming the
    ``blend`` setting: checked before training, not after it."""
    try:
        import sklearn.linear_model  # noqa: F401
        import threadpoolctl  # noqa: F401
    except ImportError as e:
        raise ConfigError(f"blend={setting!r} solves its regression with scikit-learn, which does "
                          f"not import ({e}): pip install 'tactile[train]', or set "
                          "blend=off") from None


__all__ = ["CS", "WEIGHTS", "solve", "fit", "weights", "choose", "refit", "check_available"]
