"""Pose results in the BOP 2019 CSV format: reading, writing and checking.

One line per estimate under the exact header ``scene_id,im_id,obj_id,score,R,t,time``: ``R`` is the
rotation's 9 entries in row-major order separated by spaces, ``t`` the translation in millimetres
(3 entries), ``time`` the wall-clock seconds the method took for the *whole image*, the same on
every line of an image (-1 when unknown). Inside poseflow poses are ``(4, 4)`` model-to-camera
transforms in metres; the conversion happens here.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from poseflow._cache import atomic_write
from poseflow._checks import check_tensor
from poseflow.errors import MissingFileError, ResultsFormatError, ShapeError, ValueRangeError

__all__ = ["HEADER", "ROTATION_TOLERANCE", "PoseResults", "read_results", "write_results"]

#: The header line of a BOP 2019 results file.
HEADER = "scene_id,im_id,obj_id,score,R,t,time"

#: Two times of one image that differ by more than this many seconds are an error (the toolkit's).
TIME_TOLERANCE = 1e-3

#: Largest entry of ``|R Rᵀ - I|`` and of ``|det R - 1|`` of a rotation read from a results file
#: (results written with 4 decimals pass; a scaled, reflected or zero matrix does not).
ROTATION_TOLERANCE = 1e-3


@dataclass
class PoseResults:
    """Pose estimates of a dataset, column-wise.

    Attributes:
        scene_ids: scene of each estimate, shape ``(E,)`` int64.
        im_ids: image of each estimate, shape ``(E,)`` int64.
        obj_ids: object of each estimate, shape ``(E,)`` int64.
        scores: confidences, shape ``(E,)`` float64.
        poses: model-to-camera transforms in metres, shape ``(E, 4, 4)`` float64.
        times: seconds for the estimate's image, shape ``(E,)`` float64, -1 when unknown.

    Example:
        >>> r = PoseResults.from_columns([1], [0], [5], [0.9], torch.eye(4)[None], [0.25])
        >>> len(r), r.image_times()
        (1, {(1, 0): 0.25})
    """

    scene_ids: torch.Tensor
    im_ids: torch.Tensor
    obj_ids: torch.Tensor
    scores: torch.Tensor
    poses: torch.Tensor
    times: torch.Tensor

    def __post_init__(self) -> None:
        E = self.scores.shape[0] if self.scores.dim() == 1 else -1
        for name in ("scene_ids", "im_ids", "obj_ids", "scores", "times"):
            col = getattr(self, name)
            if not isinstance(col, torch.Tensor) or col.dim() != 1 or col.shape[0] != E:
                raise ShapeError(f"{name} must be a 1-D tensor of length {E}")
        check_tensor(self.poses, "poses", (E, 4, 4), finite=True)
        if bool(self.scores.isnan().any()):
            raise ValueRangeError("scores contain NaN")

    @classmethod
    def from_columns(
        cls,
        scene_ids: Sequence[int] | torch.Tensor,
        im_ids: Sequence[int] | torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        scores: Sequence[float] | torch.Tensor,
        poses: torch.Tensor,
        times: Sequence[float] | torch.Tensor | float = -1.0,
    ) -> PoseResults:
        """Build results from columns (any int/float sequences; ``times`` may be one number)."""
        n = len(scores)
        t = torch.as_tensor(times, dtype=torch.float64)
        return cls(
            torch.as_tensor(scene_ids, dtype=torch.long).reshape(-1),
            torch.as_tensor(im_ids, dtype=torch.long).reshape(-1),
            torch.as_tensor(obj_ids, dtype=torch.long).reshape(-1),
            torch.as_tensor(scores, dtype=torch.float64).reshape(-1),
            poses.detach().to("cpu", torch.float64).reshape(-1, 4, 4),
            t.expand(n).clone() if t.dim() == 0 else t.reshape(-1),
        )

    @classmethod
    def concat(cls, parts: Iterable[PoseResults]) -> PoseResults:
        """Concatenate several result sets (e.g. one per image)."""
        parts = list(parts)
        if not parts:
            return cls.empty()
        return cls(*(torch.cat([getattr(p, f) for p in parts]) for f in _FIELDS))

    @classmethod
    def empty(cls) -> PoseResults:
        """Results with no estimate."""
        z = torch.zeros(0, dtype=torch.float64)
        zi = torch.zeros(0, dtype=torch.long)
        return cls(zi, zi.clone(), zi.clone(), z, torch.zeros(0, 4, 4, dtype=torch.float64), z)

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    def image_times(self) -> dict[tuple[int, int], float]:
        """The run time of each image, checking that all its estimates agree.

        Raises:
            ValueRangeError: two estimates of one image report times more than 1 ms apart.
        """
        out: dict[tuple[int, int], float] = {}
        for s, i, t in zip(self.scene_ids.tolist(), self.im_ids.tolist(), self.times.tolist()):
            prev = out.setdefault((s, i), t)
            if abs(prev - t) > TIME_TOLERANCE:
                raise ValueRangeError(
                    f"scene {s}, image {i}: estimates report different times ({prev} and {t})"
                )
        return out

    def average_time(self) -> float:
        """Mean time per image in seconds, or -1 when any image has no time (as the toolkit)."""
        times = list(self.image_times().values())
        if not times or any(t < 0 for t in times):
            return -1.0
        return float(sum(times) / len(times))


_FIELDS = ("scene_ids", "im_ids", "obj_ids", "scores", "poses", "times")


def write_results(path: str | os.PathLike[str], results: PoseResults) -> None:
    """Write results as a BOP 2019 CSV file (poses converted to millimetres).

    Numbers are written with Python's shortest round-trip representation, so that reading the file
    back gives the same scores and rotations and translations equal up to the mm/m rounding. The
    file is written beside ``path`` under a temporary name and renamed when complete.

    Raises:
        ValueRangeError: the estimates of one image report different times.

    Example:
        >>> import tempfile, pathlib
        >>> r = PoseResults.from_columns([1], [0], [5], [0.9], torch.eye(4)[None], [0.25])
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_results(pathlib.Path(d) / "r.csv", r)
        ...     print((pathlib.Path(d) / "r.csv").read_text().splitlines()[1])
        1,0,5,0.9,1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0,0.0 0.0 0.0,0.25
    """
    results.image_times()
    lines = [HEADER]
    R = results.poses[:, :3, :3].reshape(-1, 9).tolist()
    t = (results.poses[:, :3, 3] * 1000.0).tolist()
    for k in range(len(results)):
        lines.append(
            ",".join(
                (
                    str(int(results.scene_ids[k])),
                    str(int(results.im_ids[k])),
                    str(int(results.obj_ids[k])),
                    repr(float(results.scores[k])),
                    " ".join(repr(float(x)) for x in R[k]),
                    " ".join(repr(float(x)) for x in t[k]),
                    repr(float(results.times[k])),
                )
            )
        )
    # Written aside and renamed: an interrupted run never leaves a file that looks complete.
    text = "\n".join(lines) + "\n"
    atomic_write(path, lambda tmp: tmp.write_text(text, encoding="ascii"))


def read_results(path: str | os.PathLike[str]) -> PoseResults:
    """Read a BOP 2019 CSV results file.

    A UTF-8 byte-order mark (as some spreadsheet programs write) and Windows line ends are
    accepted. Every rotation must be a rotation: orthonormal with determinant +1, within
    :data:`ROTATION_TOLERANCE`.

    Args:
        path: the file; its first line must be exactly :data:`HEADER`.

    Returns:
        :class:`PoseResults` with poses in metres.

    Raises:
        MissingFileError: the file does not exist.
        ResultsFormatError: wrong header, a line without 7 fields, a field that is not a number,
            R without 9 or t without 3 numbers, a non-finite number, an R that is not a rotation
            (the message names the file and line), or different times for one image.
    """
    lines = _lines(path)
    if not lines or lines[0] != HEADER:
        got = lines[0] if lines else "an empty file"
        raise ResultsFormatError(f"{path}: the header must be exactly {HEADER!r}, got {got!r}")
    ints: list[tuple[int, int, int]] = []
    scores, times, mats = [], [], []
    for n, line in enumerate(lines[1:], 2):
        if line:
            ids, score, time, mat = _parse_line(line, f"{path}:{n}")
            ints.append(ids)
            scores.append(score)
            times.append(time)
            mats.append(mat)
    poses = torch.zeros(len(mats), 4, 4, dtype=torch.float64)
    if mats:
        poses[:, :3, :] = torch.tensor(mats, dtype=torch.float64).reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    ids = torch.tensor(ints, dtype=torch.long).reshape(-1, 3)
    out = PoseResults(
        ids[:, 0].clone(),
        ids[:, 1].clone(),
        ids[:, 2].clone(),
        torch.tensor(scores, dtype=torch.float64),
        poses,
        torch.tensor(times, dtype=torch.float64),
    )
    try:
        out.image_times()
    except ValueRangeError as exc:
        raise ResultsFormatError(f"{path}: {exc}") from None
    _warn_duplicates(lines[1:], path)
    return out


def _warn_duplicates(rows: list[str], path: str | os.PathLike[str]) -> None:
    """Warn when some lines repeat exactly: each copy counts as an estimate of its own.

    BOP's rule (the best-scored estimates per object and image are kept) stays the score, so
    copies can take the place of other estimates; the warning names the first repeated line.
    """
    seen: dict[str, int] = {}
    repeats = []
    for n, row in enumerate(rows, 2):
        if row and row in seen:
            repeats.append((n, seen[row]))
        seen.setdefault(row, n)
    if repeats:
        n, first = repeats[0]
        warnings.warn(
            f"{path}: {len(repeats)} line(s) repeat an earlier one exactly (line {n} is line "
            f"{first}); each copy counts as an estimate, so copies can take the place of other "
            "estimates of the same object and image",
            stacklevel=3,
        )


def _lines(path: str | os.PathLike[str]) -> list[str]:
    """The stripped lines of a text file (a UTF-8 byte-order mark dropped)."""
    if not os.path.isfile(path):
        raise MissingFileError(
            f"results file {path} does not exist (write one with `poseflow predict`, or pass "
            "--run-baseline to `poseflow eval`)"
        )
    try:
        with open(path, encoding="utf-8-sig") as f:
            return [ln.strip() for ln in f]
    except UnicodeDecodeError as exc:
        raise ResultsFormatError(f"{path} is not a text (UTF-8/ASCII) CSV file: {exc}") from None


def _parse_line(line: str, where: str) -> tuple[tuple[int, int, int], float, float, list[float]]:
    """One result: ``(scene_id, im_id, obj_id)``, score, time and the pose's top 3 rows in metres.

    Raises:
        ResultsFormatError: naming ``where`` (file and line), for any malformed field.
    """
    fields = line.split(",")
    if len(fields) != 7:
        raise ResultsFormatError(f"{where}: expected 7 comma-separated fields, got {len(fields)}")
    ids = (
        _parse(int, fields[0], where, "scene_id"),
        _parse(int, fields[1], where, "im_id"),
        _parse(int, fields[2], where, "obj_id"),
    )
    score = _parse(float, fields[3], where, "score")
    R = [_parse(float, x, where, "R") for x in fields[4].split()]
    t = [_parse(float, x, where, "t") for x in fields[5].split()]
    time = _parse(float, fields[6], where, "time")
    if len(R) != 9 or len(t) != 3:
        raise ResultsFormatError(f"{where}: R needs 9 numbers and t 3, got {len(R)} and {len(t)}")
    if not all(math.isfinite(x) for x in (score, time, *R, *t)):
        raise ResultsFormatError(f"{where}: non-finite number")
    _check_rotation(R, where)
    return (
        ids,
        score,
        time,
        [*R[0:3], t[0] / 1000.0, *R[3:6], t[1] / 1000.0, *R[6:9], t[2] / 1000.0],
    )


def _parse(kind: type, text: str, where: str, field: str) -> Any:
    """``kind(text)`` (int or float), or an error naming the file, line and field."""
    try:
        return kind(text)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise ResultsFormatError(f"{where}: {field} {text.strip()!r} is not {what}") from None


def _check_rotation(R: Sequence[float], where: str) -> None:
    """Raise unless the row-major 3x3 ``R`` is a rotation (orthonormal, determinant +1)."""
    m = torch.tensor(R, dtype=torch.float64).reshape(3, 3)
    ortho = float((m @ m.T - torch.eye(3, dtype=torch.float64)).abs().max())
    det = float(torch.linalg.det(m))
    if ortho > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        kind = "a reflection (det -1)" if abs(det + 1.0) <= ROTATION_TOLERANCE else "not a rotation"
        raise ResultsFormatError(
            f"{where}: R is {kind} (|R Rᵀ - I| = {ortho:.3g}, det R = {det:.3g}); a BOP results "
            "file holds rotation matrices, row-major"
        )
