"""The blended regression (``blend='auto'``): solve the :class:`~tactile.training.model.
WindowRegression` and choose its weight beside the LSTM on the validation windows.

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

from tactile.training.evaluate import predict

CS = (0.01, 0.1, 1.0, 10.0)
"""Inverse L2 strengths tried (scikit-learn's ``C``, ``bench/baselines.py``'s grid); ties: the
smaller."""
WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)
"""The regression's weights tried; ties: the smaller (0: the LSTM alone)."""
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
    dev = regression.coef.device
    with torch.no_grad():
        return torch.cat([regression.features(f[i : i + batch].to(dev)).cpu()
                          for i in range(0, len(f), batch)])


def fit(regression, f: torch.Tensor, y: np.ndarray, c: float, warm: bool = False) -> None:
    """Set ``regression``'s standardisation from the windows' features ``f`` (N, T, F) and
    its weights to the solution for ``c`` on them (``warm``: going on from its weights)."""
    x = _features(regression, f).double().numpy()
    mean, std = x.mean(axis=0), x.std(axis=0)
    scale = np.where(std > 1e-6, 1.0 / np.maximum(std, 1e-6), 0.0)  # constant: left out
    start = None
    if warm:
        start = (regression.coef.double().cpu().numpy(),
                 regression.intercept.double().cpu().numpy())
    coef, intercept = solve((x - mean) * scale, y, regression.coef.shape[1], c, start)
    for name, value in (("feature_mean", mean), ("feature_scale", scale), ("coef", coef),
                        ("intercept", intercept)):
        getattr(regression, name).copy_(torch.from_numpy(value).float())


def _log_probs(regression, f: torch.Tensor) -> np.ndarray:
    regression.eval()
    with torch.no_grad():
        logits = torch.cat([regression(f[i : i + 2048].to(regression.coef.device)).cpu()
                            for i in range(0, len(f), 2048)])
        return torch.log_softmax(logits.double(), dim=1).numpy()


def _figures(log_p: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(accuracy, mean cross-entropy) of the log-probabilities ``log_p`` (N, classes)."""
    lp = log_p - np.logaddexp.reduce(log_p, axis=1, keepdims=True)
    return float((lp.argmax(1) == y).mean()), float(-lp[np.arange(len(y)), y].mean())


def choose(model, parts: dict, feats: dict, dist) -> dict:
    """After the first training (its best weights in ``model``, a :class:`Blend` head whose
    weight is still 0): ``C`` on the regression's validation accuracy, the regression solved
    on the training windows, then the weight on the mixed model's validation accuracy (a lower
    validation loss breaking ties). Rank 0's result is every process's. Returns the choice
    and its validation figures, for the run's history."""
    head = model.head
    reg = head.regression
    y_tr, y_val = parts["train"].y, parts["val"].y
    val_acc = {}
    solutions = {}
    for i, c in enumerate(CS):  # ascending C, each going on from the last
        fit(reg, feats["train"], y_tr, c, warm=i > 0)
        solutions[c] = copy.deepcopy(reg.state_dict())
        val_acc[c] = _figures(_log_probs(reg, feats["val"]), y_val)[0]
    best_c = max(CS, key=lambda c: (val_acc[c], -c))
    reg.load_state_dict(solutions[best_c])
    head.mix.zero_()
    recurrent = np.log(predict(model, parts["val"], feats=feats["val"]).astype(np.float64)
                       + 1e-300)
    regression = _log_probs(reg, feats["val"])
    mixed = {w: _figures((1 - w) * recurrent + w * regression, y_val) for w in WEIGHTS}
    best_w = WEIGHTS[0]
    for w in WEIGHTS[1:]:  # more accurate, or as accurate with a lower loss (by > 1e-9)
        (acc, loss), (best_acc, best_loss) = mixed[w], mixed[best_w]
        if acc > best_acc + 1e-12 or (abs(acc - best_acc) <= 1e-12 and loss < best_loss - 1e-9):
            best_w = w
    head.mix.fill_(best_w)
    dist.sync_buffers(head)  # (each process solved alike; rank 0's is kept)
    return {"c": best_c, "mix": best_w, "val_acc": mixed[best_w][0],
            "regression_val_acc": val_acc[best_c], "recurrent_val_acc": mixed[0.0][0]}


def refit(model, w, f: torch.Tensor, choice: dict, dist) -> None:
    """The regression solved again on the windows ``w`` (features ``f``: training +
    validation) with the chosen ``C``; the chosen weight set."""
    head = model.head
    fit(head.regression, f, w.y, float(choice["c"]), warm=True)
    head.mix.fill_(float(choice["mix"]))
    dist.sync_buffers(head)


__all__ = ["CS", "WEIGHTS", "solve", "fit", "choose", "refit"]
