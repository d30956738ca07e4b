"""What the viewer knows of the running graph: the latest of each thing, thread-safe (no rclpy).

The view node writes it from its DDS subscriptions; the Foxglove server and the browser page
read it. Every entry carries a version number that grows by one on each update, so a reader
can tell "new since I last looked" without copying, and :meth:`ViewState.wait_newer` blocks
until something changes (or a timeout passes).

Units are SI: points in metres in the cloud's frame (``v0`` for the reconstructor's clouds),
stamps in seconds, voltages in volts, pixel coordinates in pixels.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

#: Most points the state keeps of one cloud (a decimated copy beyond this; the browser and a
#: slow client must not be handed a gigabyte). The full cloud still goes out on Foxglove.
MAX_VIEW_POINTS = 2_000_000


@dataclass(frozen=True)
class CloudView:
    """One point cloud: ``xyz`` (N, 3) float32 [m] in ``frame_id``; ``intensity`` (N,) float32."""

    frame_id: str
    stamp: float
    xyz: np.ndarray
    intensity: np.ndarray
    points_total: int  # before any decimation to MAX_VIEW_POINTS


@dataclass(frozen=True)
class ImageView:
    """One camera image (H, W) uint8 or uint16 and the stripe centres extracted from it.

    ``stripe_uv`` is (M, 2) float32 [px] (column, row), empty when no centres arrived for
    this frame (yet).
    """

    seq: int
    stamp: float
    image: np.ndarray
    stripe_uv: np.ndarray


@dataclass(frozen=True)
class GalvoView:
    """The driver's last reported galvo state."""

    seq: int
    stamp: float
    voltages: np.ndarray  # (4,) V: U1_pan, U1_tilt, U2_pan, U2_tilt
    laser_on: bool
    status: int


@dataclass(frozen=True)
class TransformView:
    """``parent_T_child`` as a 4x4 float64 matrix [m]; ``static`` for /tf_static."""

    parent: str
    child: str
    stamp: float
    parent_T_child: np.ndarray
    static: bool


@dataclass(frozen=True)
class CalibrationView:
    """The last view of a calibration capture: its detected feature centres and its image.

    ``uv`` (N, 2) float64 [px] (column, row) from ``calibration/progress``; ``image`` is the
    camera image stamped ``stamp`` (the view's own frame, ``matched``) or, when that frame
    never arrived, the newest camera image (``matched`` false; ``None`` before any image).
    """

    stamp: float            # the view's image stamp [s]
    uv: np.ndarray
    accepted: bool
    reason: str
    image: np.ndarray | None
    image_stamp: float      # stamp of ``image`` [s] (0 without one)
    matched: bool


@dataclass
class ViewState:
    """The latest cloud, image, galvo state, transforms, progress, diagnostics, and the
    calibration's instruction, progress and last view."""

    _lock: threading.Condition = field(default_factory=threading.Condition, repr=False)
    _version: int = 0
    _versions: dict = field(default_factory=dict)
    cloud: CloudView | None = None
    image: ImageView | None = None
    galvo: GalvoView | None = None
    transforms: dict = field(default_factory=dict)    # child frame -> TransformView
    progress: dict = field(default_factory=dict)      # e.g. {'frames_done': 10, ...}
    diagnostics: dict = field(default_factory=dict)   # status name -> {key: value (str)}
    counts: dict = field(default_factory=dict)        # messages received, by topic
    reference: CloudView | None = None  # the cloud the page measures the live cloud against
    #: calibration/instruction and calibration/progress as plain dicts (SI units), or None
    instruction: dict | None = None
    calibration_progress: dict | None = None
    calibration_view: CalibrationView | None = None

    def _bump(self, key: str) -> None:
        # caller holds the lock
        self._version += 1
        self._versions[key] = self._version
        self._lock.notify_all()

    def version(self, key: str | None = None) -> int:
        """Version of ``key`` ('cloud', 'image', ...), or of the whole state with ``None``."""
        with self._lock:
            return self._version if key is None else self._versions.get(key, 0)

    def wait_newer(self, version: int, timeout: float) -> int:
        """Block until the state's version exceeds ``version`` or ``timeout`` [s] passes."""
        with self._lock:
            self._lock.wait_for(lambda: self._version > version, timeout=timeout)
            return self._version

    def count(self, topic: str) -> None:
        with self._lock:
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def set_cloud(self, cloud: CloudView) -> None:
        with self._lock:
            self.cloud = cloud
            self._bump('cloud')

    def set_image(self, image: ImageView) -> None:
        with self._lock:
            self.image = image
            self._bump('image')

    def set_stripe(self, seq: int, stripe_uv: np.ndarray) -> None:
        """Attach stripe centres to the current image if it is frame ``seq``."""
        with self._lock:
            if self.image is not None and self.image.seq == seq:
                self.image = ImageView(self.image.seq, self.image.stamp, self.image.image,
                                       np.asarray(stripe_uv, np.float32).reshape(-1, 2))
                self._bump('image')

    def set_galvo(self, galvo: GalvoView) -> None:
        with self._lock:
            self.galvo = galvo
            self._bump('galvo')

    def set_transform(self, tf: TransformView) -> None:
        with self._lock:
            self.transforms[tf.child] = tf
            self._bump('tf')

    def set_progress(self, progress: dict) -> None:
        with self._lock:
            self.progress = dict(progress)
            self._bump('progress')

    def set_diagnostics(self, name: str, values: dict) -> None:
        with self._lock:
            self.diagnostics[name] = dict(values)
            self._bump('diagnostics')

    def set_reference(self, reference: CloudView | None) -> None:
        """Set (or clear, with ``None``) the reference cloud the page colours errors against."""
        with self._lock:
            self.reference = reference
            self._bump('reference')

    def set_instruction(self, instruction: dict) -> None:
        with self._lock:
            self.instruction = dict(instruction)
            self._bump('instruction')

    def set_calibration_progress(self, progress: dict) -> None:
        with self._lock:
            self.calibration_progress = dict(progress)
            self._bump('calibration_progress')

    def set_calibration_view(self, view: CalibrationView) -> None:
        with self._lock:
            self.calibration_view = view
            self._bump('calibration_view')

    def snapshot(self) -> dict:
        """A consistent shallow copy of every entry (arrays are not copied: never mutate them)."""
        with self._lock:
            return {'version': self._version, 'cloud': self.cloud, 'image': self.image,
                    'galvo': self.galvo, 'transforms': dict(self.transforms),
                    'progress': dict(self.progress), 'diagnostics': dict(self.diagnostics),
                    'counts': dict(self.counts), 'reference': self.reference,
                    'instruction': self.instruction,
                    'calibration_progress': self.calibration_progress,
                    'calibration_view': self.calibration_view}
