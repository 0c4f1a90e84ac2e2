"""Geometric verification of merge candidates on the map's thumbnails.

The merge rule's lookalike tests (the contrast gate and the unmapped-place veto,
:mod:`sprint_map.merge.rule`) refuse many runs that are right: under rain or snow a drive's
match looks no better than a parallel drive of the same street that the map holds unmerged,
and the tests cannot tell that rival from a lookalike street. Where the drive and the map both
keep thumbnails (``ingest --thumbnails``), a refused run can be checked on the images
themselves: ORB keypoints of the query frame and of the matched map image, matched with
Lowe's ratio test, and a fundamental matrix fitted by RANSAC. Two views of one place share
many inliers; two different streets share about as many as random pairs of images do
(14-20 with these settings, on rendered cities, on the corridor and on Nordland).

Verification is **positive evidence only**: a run with many inliers is merged although a
lookalike test refused it; a run with few is left to the merge rule as before, never
refused for it. Few inliers are weak evidence of a different place (other light, another
lane, a low resolution: the corridor's true pairs score 22 on thumbnails, near chance), many
are strong evidence of the same one (``docs/decisions.md``, "Geometric verification as
positive evidence only"). A copied street (the same facades elsewhere) verifies
as well as the right one; the rule's other tests still stand against it.

A run is verified stretch by stretch, on samples every :data:`SAMPLE_EVERY` frames. A sample
scores its inliers with its map image, or 0 when the query frame also shares
:data:`SAMPLE_MIN_INLIERS` with a *control*, the map image :data:`CONTROL_OFFSET` images away on
the same drive: then something in view matches everywhere (a bonnet, a watermark, a static
overlay) and the inliers say nothing of the place. A sample counts when the median of it and
its two neighbours reaches :data:`SAMPLE_MIN_INLIERS`, and a
stretch of consecutive counting samples is verified when it spans at least ``min_run`` frames
and its samples' median reaches ``min_inliers`` (``MapConfig.merge_verify_inliers``). So a
run right at first and wrong from some frame on keeps only its right part.

OpenCV is imported when the first thumbnail is verified, not with this module.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sprint_map.merge.rule import MergeDecision, run_ids, run_members

__all__ = ["CONTROL_OFFSET", "FEATURE_CACHE", "LocalFeatures", "MIN_WIDTH", "REVISIT_SAMPLES",
           "RunVerifier", "SAMPLE_EVERY", "SAMPLE_MIN_INLIERS", "WORK_WIDTH", "inliers",
           "local_features"]

#: Width (pixels) a thumbnail is resized to before keypoints are found: the map's thumbnails
#: are 96 pixels wide, too small for ORB's patches.
WORK_WIDTH = 288
#: Narrowest thumbnail verified: a frame smaller than a thumbnail (96 pixels wide) holds too
#: little detail for keypoints (Nordland's 64x32 frames give a true pair as many inliers as a
#: random one), so it gets none, without the cost of looking.
MIN_WIDTH = 96
#: Keypoints per image, and the ORB settings for small, smooth images.
ORB_FEATURES = 800
ORB_FAST_THRESHOLD = 5
ORB_PATCH = 15
#: Lowe's ratio test on the two nearest descriptors.
RATIO = 0.8
#: RANSAC reprojection threshold (pixels at :data:`WORK_WIDTH`) of the fundamental matrix.
RANSAC_PX = 2.0
#: Fewest ratio-test matches a fundamental matrix is fitted to.
MIN_MATCHES = 8
#: Frames between two verified samples of a run.
SAMPLE_EVERY = 5
#: Map images whose keypoints a verifier keeps (least recently used dropped first): ~32 KiB each.
FEATURE_CACHE = 256
#: Images between a sample's map image and its control image (see :meth:`RunVerifier.verified`).
CONTROL_OFFSET = 50
#: Inliers (median of a sample and its two neighbours) for a sample to count: at the top of
#: what two unrelated images share, so a stretch bridges a weak sample or two (the stretch's
#: own median must still reach ``merge_verify_inliers``).
SAMPLE_MIN_INLIERS = 22
#: Pairs of the drive's own frames matched to check a revisit (:meth:`RunVerifier.contradicted`).
REVISIT_SAMPLES = 3


@dataclass(frozen=True)
class LocalFeatures:
    """ORB keypoints of one image: ``points`` (N, 2) float32 pixels, ``descriptors`` (N, 32)
    uint8 (None when N is 0)."""

    points: np.ndarray
    descriptors: np.ndarray | None

    def __len__(self) -> int:
        return len(self.points)


def _cv2() -> Any:
    import cv2  # loaded with the first verification, not with the package

    return cv2


def local_features(jpeg: bytes) -> LocalFeatures:
    """The ORB keypoints of a thumbnail (JPEG bytes), found at :data:`WORK_WIDTH`.

    Undecodable bytes, and a thumbnail narrower than :data:`MIN_WIDTH`, give no keypoints.
    O(pixels).

    Examples
    --------
    >>> import cv2, numpy as np
    >>> rng = np.random.default_rng(0)
    >>> image = cv2.resize(rng.integers(0, 255, (24, 32), dtype=np.uint8), (96, 72))
    >>> jpeg = cv2.imencode(".jpg", image)[1].tobytes()
    >>> len(local_features(jpeg)) > 100
    True
    >>> len(local_features(b"not a jpeg"))
    0
    >>> len(local_features(cv2.imencode(".jpg", image[:, :64])[1].tobytes()))  # too small
    0
    """
    cv2 = _cv2()
    image = cv2.imdecode(np.frombuffer(jpeg, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0 or image.shape[1] < MIN_WIDTH:
        return LocalFeatures(np.zeros((0, 2), np.float32), None)
    height, width = image.shape
    size = (WORK_WIDTH, max(1, round(height * WORK_WIDTH / width)))
    image = cv2.resize(image, size, interpolation=cv2.INTER_CUBIC)
    orb = cv2.ORB_create(nfeatures=ORB_FEATURES, fastThreshold=ORB_FAST_THRESHOLD,
                         edgeThreshold=ORB_PATCH, patchSize=ORB_PATCH)
    keypoints, descriptors = orb.detectAndCompute(image, None)
    points = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2)
    return LocalFeatures(points, descriptors if len(points) else None)


def inliers(a: LocalFeatures, b: LocalFeatures) -> int:
    """How many ratio-test matches between ``a`` and ``b`` fit one fundamental matrix
    (RANSAC, :data:`RANSAC_PX`): two views of one place share many, unrelated images about
    15-20. O(N_a * N_b) for the brute-force matching.

    Examples
    --------
    >>> import cv2, numpy as np
    >>> rng = np.random.default_rng(0)
    >>> scene = cv2.resize(rng.integers(0, 255, (60, 80), dtype=np.uint8), (320, 240))
    >>> view = lambda x: cv2.imencode(".jpg", scene[20:200, x:x + 240])[1].tobytes()
    >>> inliers(local_features(view(10)), local_features(view(30))) > 100
    True
    >>> noise = cv2.imencode(".jpg", rng.integers(0, 255, (180, 240), dtype=np.uint8))[1]
    >>> inliers(local_features(view(10)), local_features(noise.tobytes())) < 30
    True
    """
    if a.descriptors is None or b.descriptors is None or min(len(a), len(b)) < 2:
        return 0
    cv2 = _cv2()
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a.descriptors, b.descriptors, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    if len(good) < MIN_MATCHES:
        return 0
    pa = a.points[[m.queryIdx for m in good]]
    pb = b.points[[m.trainIdx for m in good]]
    _, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, RANSAC_PX, 0.99)
    return 0 if mask is None else int(mask.sum())


class RunVerifier:
    """Verifies a drive's candidate runs against the map's thumbnails.

    Parameters
    ----------
    query : sequence of bytes
        The drive's thumbnails, one per frame.
    map_thumbnail : callable
        ``(seq_id, image_id) -> bytes | None``: a map frame's thumbnail (None: not kept, or
        no such frame).
    min_inliers : int
        A stretch's median inliers for it to be verified (``merge_verify_inliers``).
    min_run : int
        Fewest frames a verified stretch spans (``merge_min_run``).
    """

    def __init__(self, query: Sequence[bytes],
                 map_thumbnail: Callable[[int, int], bytes | None],
                 min_inliers: int, min_run: int) -> None:
        self.query = query
        self.map_thumbnail = map_thumbnail
        self.min_inliers = min_inliers
        self.min_run = min_run
        self._features: OrderedDict[tuple[int, int], LocalFeatures] = OrderedDict()
        #: Samples verified so far (one inlier count each).
        self.samples = 0

    def verified(self, decisions: Sequence[MergeDecision], candidates: np.ndarray,
                 max_gap: int, max_rate: float, skip: np.ndarray | None = None
                 ) -> np.ndarray:
        """Which frames of the ``candidates`` (a boolean mask over ``decisions``, the frames
        a merge rule without its lookalike tests accepts) lie on verified stretches.

        Runs are those of :func:`sprint_map.merge.rule.run_ids` (``max_gap``, ``max_rate``);
        a run whose frames are all in ``skip`` (the frames the merge rule already accepts) is
        not verified.

        Notes
        -----
        O(F / SAMPLE_EVERY) matchings for F candidate frames, each O(keypoints^2): the cost
        follows the drive, never the map. Memory: the keypoints of at most
        :data:`FEATURE_CACHE` map images.
        """
        seq, img = _places(decisions)
        out = np.zeros(len(decisions), dtype=bool)
        for frames in run_members(run_ids(np.where(candidates, seq, -1), img, max_gap,
                                          max_rate)):
            if (frames[-1] - frames[0] + 1 < self.min_run
                    or (skip is not None and bool(skip[frames].all()))):
                continue
            picks = frames[::SAMPLE_EVERY]
            if picks[-1] != frames[-1]:
                picks = np.r_[picks, frames[-1]]
            counts = np.array([self._inliers(int(f), int(seq[f]), int(img[f])) for f in picks])
            for a, b in _counting_stretches(counts):
                first = frames[0] if a == 0 else picks[a]
                last = frames[-1] if b == len(picks) - 1 else picks[b]
                if (last - first + 1 >= self.min_run
                        and float(np.median(counts[a:b + 1])) >= self.min_inliers):
                    out[frames[(frames >= first) & (frames <= last)]] = True
        return out

    def contradicted(self, decisions: Sequence[MergeDecision], accepted: np.ndarray,
                     max_gap: int, max_rate: float) -> np.ndarray:
        """The frames of ``accepted`` (the frames a merge rule accepts) that a *revisit* the
        drive's own images deny leaves unproven: a boolean mask over ``decisions``.

        Two accepted runs (:func:`sprint_map.merge.rule.run_ids`) matched to the same images
        of one map sequence say the drive passed that place twice. The drive's own frames at
        :data:`REVISIT_SAMPLES` images both runs share are then matched with each other: the
        same camera under the same light, so a true second pass shares many inliers with the
        first (``docs/decisions.md``, "Revisits checked, teleports refused": medians of 67-171
        where the revisits were true, 17-19 where they were not). If their median is below ``min_inliers``, the drive drove two
        different places that both look like the map's, and at most one of the runs is right:
        each run of such a pair keeps only its stretches verified on the map's thumbnails
        (:meth:`verified`) and the rest of it is returned. A copy of a street (the same
        facades elsewhere) passes this test as it passes :meth:`verified`; frames without
        keypoints (narrower than :data:`MIN_WIDTH`, undecodable) deny nothing.

        Notes
        -----
        :data:`REVISIT_SAMPLES` matchings per pair of runs on shared images (pairs: O(R^2) for
        R runs), plus :meth:`verified` on the runs of a denied pair.
        """
        seq, img = _places(decisions)
        runs = list(run_members(run_ids(np.where(accepted, seq, -1), img, max_gap, max_rate)))
        denied: set[int] = set()
        for a, first in enumerate(runs):
            for b in range(a + 1, len(runs)):
                second = runs[b]
                if seq[first[0]] == seq[second[0]] and not self._same_place(first, second, img):
                    denied.update((a, b))
        out = np.zeros(len(decisions), dtype=bool)
        for k in sorted(denied):
            run = np.zeros(len(decisions), dtype=bool)
            run[runs[k]] = True
            out |= run & ~self.verified(decisions, run, max_gap, max_rate)
        return out

    def _same_place(self, first: np.ndarray, second: np.ndarray, img: np.ndarray) -> bool:
        """Whether two runs of the drive, on one map sequence, are the drive at one place
        twice: no images in common, or its frames on the images they share match each other
        (median inliers of :data:`REVISIT_SAMPLES` pairs at least ``min_inliers``)."""
        lo = max(int(img[first].min()), int(img[second].min()))
        hi = min(int(img[first].max()), int(img[second].max()))
        if hi < lo:
            return True
        targets = sorted({round(lo + (hi - lo) * (i + 1) / (REVISIT_SAMPLES + 1))
                          for i in range(REVISIT_SAMPLES)})
        scores = []
        for image in targets:
            fa = int(first[np.argmin(np.abs(img[first] - image))])
            fb = int(second[np.argmin(np.abs(img[second] - image))])
            if max(fa, fb) >= len(self.query):
                continue
            a, b = local_features(self.query[fa]), local_features(self.query[fb])
            if len(a) and len(b):  # frames too small to look at (MIN_WIDTH) deny nothing
                scores.append(inliers(a, b))
        return not scores or float(np.median(scores)) >= self.min_inliers

    def _inliers(self, frame: int, seq_id: int, image_id: int) -> int:
        """A sample's score: its inliers with its map image, 0 if the control image (the first
        of ``image_id -/+ CONTROL_OFFSET`` the map holds) shares as many as a counting sample
        or there is none."""
        self.samples += 1
        mapped = self.map_thumbnail(seq_id, image_id)
        if mapped is None or frame >= len(self.query):
            return 0
        query = local_features(self.query[frame])
        score = inliers(query, self._mapped((seq_id, image_id), mapped))
        if score < SAMPLE_MIN_INLIERS:
            return score
        for control in (image_id - CONTROL_OFFSET, image_id + CONTROL_OFFSET):
            other = self.map_thumbnail(seq_id, control) if control >= 0 else None
            if other is not None:
                static = inliers(query, self._mapped((seq_id, control), other))
                return 0 if static >= SAMPLE_MIN_INLIERS else score
        return 0

    def _mapped(self, key: tuple[int, int], jpeg: bytes) -> LocalFeatures:
        """A map image's keypoints, kept for the next samples that land on it."""
        if key in self._features:
            self._features.move_to_end(key)
            return self._features[key]
        features = self._features[key] = local_features(jpeg)
        if len(self._features) > FEATURE_CACHE:
            self._features.popitem(last=False)
        return features


def _places(decisions: Sequence[MergeDecision]) -> tuple[np.ndarray, np.ndarray]:
    """The ``(seq_id, image_id)`` of every decision as two int64 arrays, -1 for "no match"."""
    seq = np.array([-1 if d.seq_id is None else d.seq_id for d in decisions], np.int64)
    img = np.array([-1 if d.image_id is None else d.image_id for d in decisions], np.int64)
    return seq, img


def _counting_stretches(counts: np.ndarray) -> list[tuple[int, int]]:
    """Maximal ``(first, last)`` index stretches of samples whose median with their two
    neighbours reaches :data:`SAMPLE_MIN_INLIERS`. O(len(counts))."""
    n = len(counts)
    ok = [float(np.median(counts[max(i - 1, 0):i + 2])) >= SAMPLE_MIN_INLIERS for i in range(n)]
    out, start = [], None
    for i, good in enumerate([*ok, False]):
        if good and start is None:
            start = i
        elif not good and start is not None:
            out.append((start, i - 1))
            start = None
    return out
