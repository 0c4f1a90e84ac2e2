"""MapLocalizing: how :class:`~sprint_map.map.SprintMap` localises a drive without changing
the map: a streaming localizer, a whole drive causal, lagged or smoothed, and the sources
(images, video, ``.npy``, ROS bags) that give a drive's descriptors in the map's space.

A mixin of the facade; a map open read-only is enough. What a localizer is made of (the view,
the centring, the GNSS aid) comes from the map's service API
(:attr:`SprintMap.service <sprint_map.map.SprintMap.service>`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.errors import DescriptorShapeError, InputError
from sprint_map.facade.reading import MapReading
from sprint_map.hmm.config import HMMConfig
from sprint_map.util import dataclass_dict
from sprint_map.util.arrays import DescriptorsLike
from sprint_map.util.validation import decode_text

if TYPE_CHECKING:  # imported where used: reading a map needs no HMM and no OpenCV
    from sprint_map.frontend.bags import BagOptions
    from sprint_map.frontend.sources import FrameSource, ProgressCallback
    from sprint_map.localize.localizer import FrameDecision, Localizer, Timing

__all__ = ["MapLocalizing"]


class MapLocalizing(MapReading):
    """The facade's localisation (see the module docstring)."""

    def localizer(self, hmm: HMMConfig | None = None, *, record: bool = False,
                  fixes: np.ndarray | None = None, **overrides: Any) -> Localizer:
        """A streaming :class:`Localizer` for one query sequence (read-only use of the map).

        Parameters
        ----------
        hmm : HMMConfig, optional
            Model parameters; default the map's own.
        record : bool
            Keep each frame's hits for :meth:`smoothed`.
        fixes : numpy.ndarray, optional
            The drive's GNSS fixes (see :meth:`ingest`), frame ``i`` the ``i``-th step.
        **overrides
            Fields of the HMM config replaced for this query only (e.g. ``k=5``).

        Returns
        -------
        Localizer
            Fed frame by frame (``step``) or a whole drive (``localize``).

        Raises
        ------
        InputError
            ``fixes`` out of range.
        ConfigError
            An override that is not an HMM parameter, or out of its range.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 40}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     decisions = m.localizer(k=5).localize(road[:20])
        ...     print(len(decisions), decisions[-1].image_id)
        20 19
        """
        from sprint_map.localize.localizer import Localizer

        base = hmm or self.config.hmm
        return Localizer(self, dataclass_dict.replace(base, **overrides) if overrides else base,
                         record=record, gnss=self.service.gnss_aid(fixes, None))

    def localize(self, descriptors: Any, *, smooth: bool = False, lag: int = 0,
                 thumbnails: Sequence[bytes] | None = None,
                 observe: Callable[[Localizer], None] | None = None,
                 hmm: HMMConfig | None = None, fixes: np.ndarray | None = None,
                 **overrides: Any) -> tuple[list[FrameDecision], Timing]:
        """Localise a whole query drive without changing the map: the one call behind
        ``localize`` (with or without ``--smooth`` and ``--trace``) and ``eval``.

        Parameters
        ----------
        descriptors : array_like or iterable of array_like
            An (N, dim) array or an iterable of row batches (streamed; searches are batched).
        smooth : bool
            False: the causal filter's decisions, as a vehicle gets them; True: the after-drive
            pipeline's (:func:`sprint_map.merge.smoothing.smoothed_decisions`, what ``ingest``
            merges, given the same ``thumbnails``).
        lag : int
            Frames: answer each frame once ``lag`` more were seen, from the fixed-lag smoothed
            posterior (:class:`~sprint_map.localize.lagged.LaggedLocalizer`; 0: causal).
        thumbnails : sequence of bytes, optional
            One JPEG per frame, for ``smooth``'s verification.
        observe : callable, optional
            Receives the localizer before the first frame (e.g. :meth:`TraceRecorder.attach
            <sprint_map.localize.trace.TraceRecorder.attach>`).
        hmm : HMMConfig, optional
            Replaces the map's HMM config for this query only, as do ``overrides``.
        fixes : numpy.ndarray, optional
            The drive's GNSS fixes (see :meth:`ingest`; one per frame, checked).
        **overrides
            Fields of the HMM config replaced for this query only.

        Returns
        -------
        tuple of (list of FrameDecision, Timing)
            One decision per frame, in frame order, and where the time went.

        Raises
        ------
        InputError
            A bad ``lag``, or a lag with ``smooth``, ``observe``, ``thumbnails`` or ``fixes``
            (:func:`~sprint_map.localize.lagged.validate_lag`); fixes not one per frame.
        DescriptorShapeError
            Descriptors that are not (N, dim).
        ConfigError
            An override that is not an HMM parameter, or out of its range.

        Notes
        -----
        Per frame: one k-NN search (batched) and one HMM step over the active set; with
        ``smooth``, the pipeline's passes (O(live) per frame each) and O(k) hits kept per frame;
        with ``lag``, ``lag`` backward steps more per frame.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 40}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     causal, _ = m.localize(road[10:30])
        ...     lagged, _ = m.localize(road[10:30], lag=3)
        ...     print([d.image_id for d in causal[-3:]], len(lagged))
        [27, 28, 29] 20
        """
        if lag:
            from sprint_map.localize.lagged import LaggedLocalizer, validate_lag

            validate_lag(lag, whole_drive=smooth or observe is not None or thumbnails is not None,
                         fixes=fixes is not None)
            base = hmm or self.config.hmm
            lagged = LaggedLocalizer(self, lag, dataclass_dict.replace(base, **overrides)
                                     if overrides else base)
            batches = np.asarray(descriptors) if isinstance(descriptors, np.ndarray | list) \
                else descriptors
            return lagged.localize(batches), lagged.timing
        batches = np.asarray(descriptors) if isinstance(descriptors, np.ndarray | list) \
            else descriptors
        if fixes is not None and isinstance(batches, np.ndarray):
            self.service.gnss_aid(fixes, len(batches), index=False)
        localizer = self.localizer(hmm, record=smooth, fixes=fixes, **overrides)
        if observe is not None:
            observe(localizer)
        decisions = localizer.localize(batches)
        if fixes is not None:
            self.service.gnss_aid(fixes, len(decisions), index=False)
        if smooth:
            decisions = self.smoothed(localizer, thumbnails=thumbnails)
        return decisions, localizer.timing

    def smoothed(self, localizer: Any, descriptors: DescriptorsLike | None = None,
                 thumbnails: Sequence[bytes] | None = None) -> list[FrameDecision]:
        """The after-drive decisions of the drive ``localizer`` has seen, as
        :func:`sprint_map.merge.smoothing.smoothed_decisions` makes them; a proxy of a
        localiser in another process (the service's Ray replicas) makes them there, through
        its own ``smoothed(descriptors)``.

        Parameters
        ----------
        localizer : Localizer
            Made with ``record=True`` (:meth:`localizer`), after the drive.
        descriptors : array_like, optional
            The drive's rows: let the deep pass search a drive recorded shallower than
            ``smooth_k`` (the service's sessions).
        thumbnails : sequence of bytes, optional
            One JPEG per frame: verify refused runs on the images.

        Returns
        -------
        list of FrameDecision
            One per frame seen, in frame order.

        Raises
        ------
        ValueError
            ``localizer`` was not made with ``record=True``.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 40}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     localizer = m.localizer(record=True)
        ...     _ = localizer.localize(road[5:25])
        ...     print([d.image_id for d in m.smoothed(localizer)[:3]])
        [5, 6, 7]
        """
        from sprint_map.localize.localizer import Localizer
        from sprint_map.merge.smoothing import smoothed_decisions

        if not isinstance(localizer, Localizer):
            decisions: list[FrameDecision] = localizer.smoothed(descriptors)
            return decisions
        if descriptors is not None:  # the drive as described, centred as it was localised
            descriptors = localizer.centring.fresh().apply(np.asarray(descriptors))
        return smoothed_decisions(localizer, self, descriptors, thumbnails)

    def open_source(self, path: str | os.PathLike[str], *, stride: int = 1,
                    progress: ProgressCallback | None = None,
                    thumbnails: bool = False, bag: BagOptions | None = None) -> FrameSource:
        """Open images, a video, a ``.npy`` or a ROS bag as descriptors that fit this map.

        Parameters
        ----------
        path : str or path
            The source.
        stride : int
            Keep every ``stride``-th frame.
        progress : callable, optional
            Told of the frames read (:data:`~sprint_map.frontend.sources.ProgressCallback`).
        thumbnails : bool
            Also make a small JPEG of each frame (``source.thumbnails``, for :meth:`ingest`);
            images, video and bags only.
        bag : BagOptions, optional
            A bag's topics and ``every_m`` (:mod:`sprint_map.frontend.bags`); its GNSS
            positions are ``source.positions`` (for :meth:`metric_positions`).

        Returns
        -------
        FrameSource
            Its ``iter_batches()`` and ``read_all()`` give the descriptors.

        Raises
        ------
        InputError
            Images or video given to a map of precomputed descriptors; a path that is not
            UTF-8 text (OpenCV would crash on it, and it would name the sequence).
        DescriptorShapeError
            A ``.npy`` whose dimension is not the map's.

        Examples
        --------
        >>> import tempfile, numpy as np
        >>> from sprint_map import MapConfig, SprintMap
        >>> folder = tempfile.mkdtemp()
        >>> np.save(folder + "/drive.npy", np.ones((12, 16), np.float32))
        >>> with SprintMap.create(folder + "/city.map", MapConfig(dim=16)) as m:
        ...     print(m.open_source(folder + "/drive.npy").read_all().shape)
        (12, 16)
        """
        spec = self.config.descriptor_spec()
        src = Path(decode_text(os.fspath(path), "source path"))
        if spec is None and src.suffix.lower() != ".npy":
            raise InputError(
                f"{src}: this map holds precomputed descriptors (dim {self.config.dim}); give a "
                ".npy of descriptors, or create the map with --descriptor hog for images/video"
            )
        if thumbnails and spec is None:
            raise InputError(f"{src}: thumbnails need images or video, and this map holds "
                             "precomputed descriptors")
        from sprint_map.frontend.sources import open_source

        source = open_source(src, spec, stride=stride, progress=progress,
                             thumbnails=thumbnails, bag=bag)
        if source.dim != self.config.dim:
            raise DescriptorShapeError(
                f"{src}: descriptors have {source.dim} dimensions, the map has {self.config.dim}"
            )
        if spec is not None and spec.kind == "onnx":
            from sprint_map.frontend.onnx_model import unverified_files

            unverified = unverified_files(spec.params)
            if unverified and not any("weights file" in w for w in self.warnings):
                self.warnings.append(
                    f"the map records the digest of {spec.params['model']} only (made before "
                    f"weights files were): its weights file(s) {', '.join(unverified)} are "
                    "not verified")
        return source
