"""The two-class classifier pi_h over windows, with rest as a third class, and its offline
metrics.

Linear discriminant analysis (scikit-learn's, shrinkage "auto": few windows, many
features) on standardised features. Classes: -1 and +1 (the person's two commands) and
0, rest (nothing asked of the arm). A window's class probabilities are LDA's posterior;
a window whose largest probability is below ``reject_below`` is rejected (no class), and
a majority vote over the last ``vote`` windows smooths the stream (the field's standard
post-processing). The fitted model is kept as plain numbers (means, scales,
coefficients, intercepts) and rebuilt without pickle: a calibration file can carry no
code.

Offline metrics (LibEMG's definitions): classification accuracy over accepted windows,
active error rate (wrong among accepted windows of the two commands), instability
(changes of the decision between consecutive windows), rejection rate; and the
confusion matrix (rows: the true class; columns: the decided one, then "rejected").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

CLASSES = (-1, 0, 1)
"""-1 and +1: the person's commands u_h; 0: rest."""
REJECTED = 99
"""The label of a rejected window."""
LABEL_NOISE = 0.05
"""The share of calibration windows whose cue may not match what the muscles did."""
CLASS_NAMES = {-1: "-1", 0: "rest", 1: "+1", REJECTED: "rejected"}


class LinearClassifier(BaseModel):
    """An LDA's decision functions on standardised features, as plain numbers."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    classes: tuple[int, ...]
    mean: list[float]
    scale: list[float]
    coef: list[list[float]]  # (classes, features)
    intercept: list[float]  # (classes,)
    temperature: float = Field(1.0, gt=0, le=1e6)
    """Scores are divided by this before the softmax (fitted on held-out windows)."""

    @model_validator(mode="after")
    def _shapes(self) -> LinearClassifier:
        n, k = len(self.mean), len(self.classes)
        if tuple(sorted(self.classes)) != CLASSES or len(self.scale) != n:
            raise ValueError(f"a classifier of the classes {CLASSES}, one scale per feature")
        if len(self.intercept) != k or len(self.coef) != k or any(len(r) != n for r in self.coef):
            raise ValueError(f"coefficients ({k}, {n}) and {k} intercepts expected")
        if not np.all(np.isfinite(self.coef)) or min(self.scale) <= 0:
            raise ValueError("coefficients must be finite and scales positive")
        return self

    @property
    def features(self) -> int:
        return len(self.mean)

    def scores(self, features: np.ndarray) -> np.ndarray:
        """LDA's decision functions (m, 3) of features (m, n)."""
        z = (np.atleast_2d(features) - np.array(self.mean)) / np.array(self.scale)
        return np.asarray(z @ np.array(self.coef).T + np.array(self.intercept))

    def probabilities(self, features: np.ndarray) -> np.ndarray:
        """Class probabilities (m, 3) in ``self.classes`` order, of features (m, n)."""
        return softmax(self.scores(features) / self.temperature)


def softmax(scores: np.ndarray) -> np.ndarray:
    """Row-wise softmax (sklearn's LDA turns its scores into probabilities so)."""
    shifted = scores - scores.max(axis=1, keepdims=True)
    p = np.exp(shifted)
    return np.asarray(p / p.sum(axis=1, keepdims=True))


def fit_temperature(scores: np.ndarray, labels: np.ndarray, classes: tuple[int, ...]) -> float:
    """The temperature that makes held-out probabilities honest (Guo et al. 2017): LDA's
    shared covariance gives log-odds of hundreds on well-separated EMG, "certain" even
    when wrong; dividing the scores by T fitted by maximum likelihood on windows the
    classifier never saw makes its probability of a class mean what it says. The fit
    allows ``LABEL_NOISE`` of the cues to be wrong (a mixture with a uniform guess)."""
    from scipy.optimize import minimize_scalar

    index = np.searchsorted(np.array(classes), labels)

    def loss(log_t: float) -> float:
        p = softmax(scores / np.exp(log_t))[np.arange(len(index)), index]
        # a cue is not the muscle: a few windows are labelled wrongly (a late reaction, an
        # early release); without this allowance they alone would flatten every probability
        return float(-np.mean(np.log((1 - LABEL_NOISE) * p + LABEL_NOISE / len(classes))))

    return float(np.exp(minimize_scalar(loss, bounds=(-5, 12), method="bounded").x))


def fit(features: np.ndarray, labels: np.ndarray) -> LinearClassifier:
    """An LDA (shrinkage "auto", Ledoit-Wolf) of windows' features (m, n) and labels (m,)."""
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    mean = features.mean(axis=0)
    scale = features.std(axis=0)
    scale[scale < 1e-12] = 1.0  # a constant feature: left as it is
    lda = LinearDiscriminantAnalysis(solver="lsqr", shrinkage="auto")
    lda.fit((features - mean) / scale, labels)
    return LinearClassifier(
        classes=tuple(int(c) for c in lda.classes_),
        mean=mean.tolist(),
        scale=scale.tolist(),
        coef=np.atleast_2d(lda.coef_).tolist(),
        intercept=np.atleast_1d(lda.intercept_).tolist(),
    )


def decide_windows(probabilities: np.ndarray, classes: tuple[int, ...], reject_below: float,
                   vote: int) -> np.ndarray:  # fmt: skip
    """Each window's decided class: the most probable one, REJECTED below ``reject_below``,
    then the majority of the last ``vote`` accepted decisions (ties: the newest wins)."""
    best = np.argmax(probabilities, axis=1)
    raw = np.where(probabilities.max(axis=1) >= reject_below, np.array(classes)[best], REJECTED)
    voted = raw.copy()
    for k in range(len(raw)):
        recent = [c for c in raw[max(0, k - vote + 1) : k + 1] if c != REJECTED]
        voted[k] = majority(recent) if recent else REJECTED
    return voted


def majority(labels: list[int]) -> int:
    """The most frequent label; a tie goes to the newest of the tied labels."""
    counts = {c: labels.count(c) for c in labels}
    top = max(counts.values())
    return next(c for c in reversed(labels) if counts[c] == top)


@dataclass(frozen=True)
class OfflineMetrics:
    accuracy: float  # correct / accepted windows
    active_error_rate: float  # wrong / accepted windows whose true class is -1 or +1
    instability: float  # decision changes / (windows - 1)
    rejection_rate: float  # rejected / windows
    confusion: list[list[int]]  # rows: true -1, rest, +1; columns: the same, then rejected
    windows: int

    def as_dict(self) -> dict[str, object]:
        return {"accuracy": self.accuracy, "active_error_rate": self.active_error_rate,
                "instability": self.instability, "rejection_rate": self.rejection_rate,
                "confusion": self.confusion, "windows": self.windows}  # fmt: skip


def offline_metrics(truth: np.ndarray, decided: np.ndarray) -> OfflineMetrics:
    """LibEMG's offline metrics of decided windows against the cued classes."""
    accepted = decided != REJECTED
    active = accepted & (truth != 0)
    columns = (*CLASSES, REJECTED)
    confusion = [[int(np.sum((truth == t) & (decided == d))) for d in columns] for t in CLASSES]
    changes = int(np.sum(decided[1:] != decided[:-1])) if len(decided) > 1 else 0
    return OfflineMetrics(
        accuracy=_share(truth[accepted] == decided[accepted]),
        active_error_rate=_share(truth[active] != decided[active]),
        instability=changes / max(1, len(decided) - 1),
        rejection_rate=_share(~accepted),
        confusion=confusion,
        windows=len(decided),
    )


def _share(flags: np.ndarray) -> float:
    return float(np.mean(flags)) if len(flags) else 0.0


class CrossValidation(BaseModel):
    """Leave-one-block-out: each block decided by a classifier fitted on the others."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    accuracy: float = Field(ge=0, le=1)
    active_error_rate: float = Field(ge=0, le=1)
    instability: float = Field(ge=0, le=1)
    rejection_rate: float = Field(ge=0, le=1)
    confusion: list[list[int]]
    per_block_accuracy: list[float]
    temperature: float = Field(gt=0, description="fitted on the held-out scores")


def cross_validate(features: np.ndarray, labels: np.ndarray, blocks: np.ndarray,
                   trials: np.ndarray, reject_below: float, vote: int
                   ) -> CrossValidation:  # fmt: skip
    """Leave-one-block-out: every block scored by an LDA fitted on the other blocks; the
    temperature fitted on all held-out scores; then each block decided (rejection and
    vote as online, the vote starting afresh in each trial); the metrics of all held-out
    decisions together."""
    held_scores = np.zeros((len(labels), len(CLASSES)))
    for block in np.unique(blocks):
        held = blocks == block
        held_scores[held] = fit(features[~held], labels[~held]).scores(features[held])
    temperature = fit_temperature(held_scores, labels, CLASSES)
    p = softmax(held_scores / temperature)
    truth, decided, per_block = [], [], []
    for block in np.unique(blocks):
        held = blocks == block
        order = np.argsort(trials[held], kind="stable")
        out = np.concatenate([
            decide_windows(p[held][trials[held] == trial], CLASSES, reject_below, vote)
            for trial in np.unique(trials[held])
        ])  # fmt: skip
        truth.append(labels[held][order])
        decided.append(out)
        per_block.append(offline_metrics(labels[held][order], out).accuracy)
    m = offline_metrics(np.concatenate(truth), np.concatenate(decided))
    return CrossValidation(accuracy=m.accuracy, active_error_rate=m.active_error_rate,
                           instability=m.instability, rejection_rate=m.rejection_rate,
                           confusion=m.confusion, per_block_accuracy=per_block,
                           temperature=temperature)  # fmt: skip
