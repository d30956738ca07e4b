"""A GenICam camera through Aravis: open by serial or user id, features by name, frames.

A pure library (no ROS). Aravis (``libaravis-0.8``) speaks GigE Vision and USB3 Vision
itself and reads the camera's own GenICam description, so a feature is reached by its
standard name (``ExposureTime``, ``Gain``, ``PixelFormat``, ``Width`` ...) on any vendor's
camera, exactly as the camera's XML defines it. Python reaches Aravis through PyGObject
(``gi``); both come from Debian (``python3-gi``, ``gir1.2-aravis-0.8``, see
``tools/apt-packages.txt``) and are imported only when a camera is used, so the rest of
the driver works without them.

Feature values are in the camera's GenICam units (``ExposureTime`` in microseconds,
``AcquisitionFrameRate`` in hertz, sizes in pixels), as the SFNC defines them.

Loss of the device (a pulled cable, power loss) follows camera_ros' pattern: `error`
becomes a message (from the device's heartbeat, or from a control request that found no
device), and `reopen` tries to open the same device again, restores every feature set
through `set` and restarts the acquisition if it was running.

``python -m galvo_driver.genicam_camera`` lists the cameras Aravis can see.
"""

from __future__ import annotations

import math
import numbers
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

# Pixel formats a frame can carry (GenICam PFNC values, unpacked little-endian mono):
# name -> (PFNC value, bit depth). Packed formats are not accepted.
PIXEL_FORMATS = {
    "Mono8": (0x01080001, 8),
    "Mono10": (0x01100003, 10),
    "Mono12": (0x01100005, 12),
    "Mono16": (0x01100007, 16),
}
_BIT_DEPTH_BY_PFNC = {v: d for v, d in PIXEL_FORMATS.values()}
# Features that change the payload: refused while acquiring (the buffers are sized for it).
_PAYLOAD_FEATURES = ("Width", "Height", "PixelFormat", "BinningHorizontal", "BinningVertical")

_ARAVIS = None


class CameraError(RuntimeError):
    """A camera could not be found, reached or set; the message names the device and feature."""


@dataclass(frozen=True)
class CameraFrame:
    """One image from the camera.

    Attributes
    ----------
    image : np.ndarray
        (height, width) uint8 for Mono8, uint16 for Mono10/12/16 (values < 2**bit_depth).
    frame_id : int
        The camera's frame (block) id.
    timestamp_ns : int
        The camera's own clock at the frame [ns], as the camera reports it.
    bit_depth : int
        8, 10, 12 or 16.
    """

    image: np.ndarray
    frame_id: int
    timestamp_ns: int
    bit_depth: int


def _aravis():
    """Import Aravis through PyGObject once; a clear CameraError if it is not installed."""
    global _ARAVIS
    if _ARAVIS is None:
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis, GLib
        except (ImportError, ValueError) as exc:
            raise CameraError(
                "Aravis 0.8 is not reachable from Python: the Debian packages python3-gi and "
                "gir1.2-aravis-0.8 are needed (`make test-deps` installs them, and "
                f"tools/setup_venv.sh links gi into .venv): {exc}"
            ) from exc
        _ARAVIS = (Aravis, GLib)
    return _ARAVIS


def pixel_format_info(name: str) -> tuple[np.dtype, int]:
    """Numpy dtype and bit depth of a frame in pixel format `name`.

    Parameters
    ----------
    name : str
        GenICam pixel format name, e.g. ``"Mono8"`` or ``"Mono12"``.

    Returns
    -------
    (dtype, bit_depth) : (np.dtype, int)
        uint8 and 8 for Mono8; uint16 and 10/12/16 for the deeper mono formats.

    Raises
    ------
    CameraError
        For a format frames cannot carry (colour, packed).
    """
    if name not in PIXEL_FORMATS:
        raise CameraError(
            f"PixelFormat {name!r} is not supported by galvoscan "
            f"(supported: {', '.join(PIXEL_FORMATS)})"
        )
    depth = PIXEL_FORMATS[name][1]
    return np.dtype(np.uint8 if depth == 8 else np.uint16), depth


def list_cameras() -> list[dict]:
    """The cameras Aravis can see now (GigE Vision discovery, USB3 Vision enumeration).

    Returns
    -------
    list of dict
        One dict per camera: ``id`` (Aravis device id), ``vendor``, ``model``, ``serial``,
        ``address``, ``protocol``.
    """
    Aravis, _ = _aravis()
    Aravis.update_device_list()
    return [
        {
            "id": Aravis.get_device_id(i),
            "vendor": Aravis.get_device_vendor(i),
            "model": Aravis.get_device_model(i),
            "serial": Aravis.get_device_serial_nbr(i),
            "address": Aravis.get_device_address(i),
            "protocol": Aravis.get_device_protocol(i),
        }
        for i in range(Aravis.get_n_devices())
    ]


#: Feature kind -> the ArvCamera accessor suffix (``get_<suffix>`` / ``set_<suffix>``).
_ACCESSORS = {"enum": "string", "float": "float", "int": "integer", "bool": "boolean",
              "str": "string"}


class GenICamCamera:
    """One GenICam camera, opened by serial number or DeviceUserID.

    Parameters
    ----------
    serial : str, optional
        The camera's serial number (``DeviceSerialNumber``).
    user_id : str, optional
        The camera's user-defined name (``DeviceUserID``). If both are given, both must
        match; if neither, the first camera found is opened.
    packet_socket : bool
        GigE Vision only: receive through Aravis' packet-socket ring (needs CAP_NET_RAW; less
        CPU at high data rates, but a frame can wait up to 5 ms for its ring block to be
        retired). True by default: on a loaded machine the plain UDP sockets lose packets of
        large frames; False receives through them (no added latency, small frames only).
    """

    def __init__(
        self, serial: str | None = None, user_id: str | None = None, *, packet_socket: bool = True
    ):
        self.serial = serial
        self.user_id = user_id
        self.packet_socket = bool(packet_socket)
        self._label = (
            "camera "
            + " / ".join(
                x
                for x in (
                    f"serial {serial!r}" if serial else "",
                    f"user id {user_id!r}" if user_id else "",
                )
                if x
            )
            if (serial or user_id)
            else "camera (first found)"
        )
        self._cam = None
        self._dev = None
        self._stream = None
        self._n_buffers = 0
        self._want_acquiring = False  # started and not stopped by the user: reopen restarts
        self._device_id: str | None = None
        self._applied: dict[str, object] = {}
        self._stats_before = {"completed": 0, "failed": 0, "underrun": 0}
        self._error: str | None = None
        self._lock = threading.Lock()
        self._handler = None

    # -- opening ------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """Whether a device is open."""
        return self._cam is not None

    @property
    def acquiring(self) -> bool:
        """Whether `start` has been called and not `stop`."""
        return self._stream is not None

    @property
    def device_id(self) -> str | None:
        """Aravis' id of the opened device (vendor-model-serial for GigE Vision)."""
        return self._device_id

    def open(self) -> None:
        """Find the camera and open it.

        Raises
        ------
        CameraError
            If no camera matches, or the one found cannot be opened.
        """
        if self._cam is not None:
            return
        self._open_id(self._find())

    def _find(self) -> str:
        """Aravis id of the wanted camera among those seen now (never a name lookup)."""
        cams = list_cameras()
        seen = ", ".join(f"{c['serial']} ({c['id']})" for c in cams) or "none"
        if self._device_id is not None:  # reopening: the same device, nothing else
            if not any(c["id"] == self._device_id for c in cams):
                raise CameraError(
                    f"{self._label}: device {self._device_id!r} not found (cameras seen: {seen})"
                )
            return self._device_id
        if self.serial is not None:
            cams = [c for c in cams if c["serial"] == self.serial]
            if not cams:
                raise CameraError(
                    f"{self._label}: no camera with this serial number (cameras seen: {seen})"
                )
        if self.user_id is not None:
            cams = [c for c in cams if self._user_id_of(c["id"]) == self.user_id]
            if not cams:
                raise CameraError(
                    f"{self._label}: no camera with this DeviceUserID (cameras seen: {seen})"
                )
        if not cams:
            raise CameraError(f"{self._label}: no camera found")
        return cams[0]["id"]

    @staticmethod
    def _user_id_of(device_id: str) -> str | None:
        Aravis, GLib = _aravis()
        try:
            return Aravis.Camera.new(device_id).get_string("DeviceUserID")
        except (GLib.Error, AttributeError):
            return None

    def _open_id(self, device_id: str) -> None:
        Aravis, GLib = _aravis()
        try:
            cam = Aravis.Camera.new(device_id)
        except GLib.Error as exc:
            raise CameraError(
                f"{self._label}: cannot open device {device_id!r}: {exc.message}"
            ) from exc
        if cam is None:
            raise CameraError(f"{self._label}: cannot open device {device_id!r}")
        dev = cam.get_device()
        for feature, want in (("DeviceUserID", self.user_id), ("DeviceSerialNumber", self.serial)):
            if want is None:
                continue
            try:
                have = cam.get_string(feature)
            except GLib.Error:
                have = None
            if have != want:
                raise CameraError(
                    f"{self._label}: device {device_id!r} reports {feature} {have!r}"
                )
        if cam.is_gv_device():
            try:
                cam.gv_auto_packet_size()  # the largest packet the path carries (jumbo frames)
            except GLib.Error:
                pass
            cam.gv_set_stream_options(
                Aravis.GvStreamOption.NONE
                if self.packet_socket
                else Aravis.GvStreamOption.PACKET_SOCKET_DISABLED
            )
        self._cam, self._dev, self._device_id = cam, dev, device_id
        self._error = None
        self._handler = dev.connect("control-lost", self._on_control_lost)

    def _on_control_lost(self, *_args) -> None:
        # Called from Aravis' heartbeat thread.
        self._error = (f"{self._label}: control of device {self._device_id!r} lost "
                       "(unplugged or powered off?)")

    def close(self) -> None:
        """Stop acquiring and close the device (safe to call twice)."""
        self.stop()
        if self._dev is not None and self._handler is not None:
            self._dev.disconnect(self._handler)
        self._cam = self._dev = self._handler = None

    def __enter__(self) -> GenICamCamera:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def error(self) -> str | None:
        """Why the device is unusable (lost), or None while it works."""
        return self._error

    def reopen(self) -> bool:
        """Try once to open the same device again after a loss (camera_ros pattern).

        Restores every feature set through `set`, in the order set, and restarts the
        acquisition if it was running.

        Returns
        -------
        bool
            True if the device is open (and acquiring if it was), with `error` cleared.
        """
        was_acquiring, n_buffers = self._want_acquiring, self._n_buffers
        self._drop()
        try:
            self._open_id(self._find())  # discovery first: found at its (new) address
            for name, value in self._applied.items():
                self._write(name, value)
            if was_acquiring:
                self.start(n_buffers)
        except CameraError as exc:
            self._drop()
            self._error = f"{self._label}: reopen failed: {exc}"
            return False
        return True

    def _drop(self) -> None:
        """Forget the device without talking to it (it may be gone)."""
        if self._stream is not None:
            self._add_stats(self._stream)
        if self._stream is not None and self._error is None:
            try:
                self._cam.stop_acquisition()
            except Exception:  # noqa: BLE001 - the device may be gone; nothing to do
                pass
        if self._dev is not None and self._handler is not None:
            self._dev.disconnect(self._handler)
        self._stream = self._cam = self._dev = self._handler = None

    def _require_open(self):
        if self._cam is None:
            raise CameraError(f"{self._label}: not open")
        return self._cam

    def _device_call(self, what: str, fn, *args):
        """Call an Aravis method; a GLib.Error becomes CameraError, a lost device sets `error`."""
        Aravis, GLib = _aravis()
        try:
            return fn(*args)
        except GLib.Error as exc:
            lost = exc.matches(
                Aravis.device_error_quark(), Aravis.DeviceError.TIMEOUT
            ) or exc.matches(Aravis.device_error_quark(), Aravis.DeviceError.NOT_CONNECTED)
            if lost:
                self._error = (f"{self._label}: device {self._device_id!r} does not answer "
                               f"({what}): {exc.message}")
            raise CameraError(f"{self._label}: {what}: {exc.message}") from exc

    # -- features -----------------------------------------------------------------------

    def _node(self, name: str):
        cam = self._require_open()
        if not isinstance(name, str) or not name:
            raise CameraError(
                f"{self._label}: feature name must be a non-empty string, got {name!r}"
            )
        node = cam.get_device().get_feature(name)
        if node is None:
            raise CameraError(f"{self._label}: unknown feature {name!r}")
        return node

    def _kind(self, name: str) -> str:
        Aravis, _ = _aravis()
        node = self._node(name)
        for kind, iface in (
            ("enum", Aravis.GcEnumeration),
            ("float", Aravis.GcFloat),
            ("int", Aravis.GcInteger),
            ("bool", Aravis.GcBoolean),
            ("str", Aravis.GcString),
            ("command", Aravis.GcCommand),
        ):
            if isinstance(node, iface):
                return kind
        raise CameraError(
            f"{self._label}: feature {name!r} has an unsupported type {type(node).__name__}"
        )

    def get(self, name: str):
        """Read GenICam feature `name` from the camera.

        Returns
        -------
        str, float, int or bool
            Enumerations as their entry name, in the camera's units.
        """
        cam = self._require_open()
        kind = self._kind(name)
        accessor = _ACCESSORS.get(kind)
        getter = getattr(cam, f"get_{accessor}") if accessor else None
        if getter is None:
            raise CameraError(f"{self._label}: feature {name!r} is a command and has no value")
        return self._device_call(f"read {name}", getter, name)

    def feature_range(self, name: str) -> tuple:
        """The values feature `name` accepts now.

        Returns
        -------
        tuple
            (min, max) for a number, in the camera's units; the entry names for an enumeration.
        """
        cam = self._require_open()
        kind = self._kind(name)
        if kind == "enum":
            names = self._device_call(
                f"read {name} entries", cam.dup_available_enumerations_as_strings, name
            )
            return tuple(names)
        if kind == "float":
            return tuple(self._device_call(f"read {name} range", cam.get_float_bounds, name))
        if kind == "int":
            return tuple(self._device_call(f"read {name} range", cam.get_integer_bounds, name))
        raise CameraError(f"{self._label}: feature {name!r} ({kind}) has no range")

    def feature_increment(self, name: str) -> float:
        """The step between the values numeric feature `name` accepts, in the camera's units;
        0 when the camera states none (a float feature without an increment)."""
        cam = self._require_open()
        kind = self._kind(name)
        if kind == "int":
            return float(self._device_call(f"read {name} increment",
                                           cam.get_integer_increment, name))
        if kind != "float":
            raise CameraError(f"{self._label}: feature {name!r} ({kind}) has no increment")
        try:
            inc = float(cam.get_float_increment(name))
        except Exception:  # noqa: BLE001 - a float without an <Inc> node: no grid
            return 0.0
        return inc if math.isfinite(inc) and inc > 1e-9 else 0.0

    def set(self, name: str, value) -> None:
        """Write GenICam feature `name`, after checking `value` against the camera's own limits.

        Parameters
        ----------
        name : str
            Feature name, e.g. ``"ExposureTime"`` [us], ``"Gain"``, ``"PixelFormat"``.
        value : str, float, int or bool
            In the camera's units; an enumeration takes an entry name.

        Raises
        ------
        CameraError
            Unknown feature, read-only feature, wrong type, NaN/infinite, out of range, not
            on the increment, unknown enumeration entry, or a payload change while
            acquiring. The camera is left unchanged.
        """
        cam = self._require_open()
        kind = self._kind(name)
        node = self._node(name)
        Aravis, _ = _aravis()
        if kind == "command":
            raise CameraError(f"{self._label}: feature {name!r} is a command, not a value")
        if node.get_actual_access_mode() not in (Aravis.GcAccessMode.RW, Aravis.GcAccessMode.WO):
            raise CameraError(f"{self._label}: feature {name!r} is not writable now")
        if self.acquiring and name in _PAYLOAD_FEATURES:
            raise CameraError(
                f"{self._label}: feature {name!r} changes the image size; stop acquiring first"
            )
        value = self._checked(cam, name, kind, value)
        self._write(name, value)
        self._applied.pop(name, None)
        self._applied[name] = value

    def _checked(self, cam, name: str, kind: str, value):
        """`value` converted to the feature's type, or CameraError naming what is wrong."""
        bad = f"{self._label}: feature {name!r}"
        if kind == "enum":
            entries = self.feature_range(name)
            if not isinstance(value, str) or value not in entries:
                raise CameraError(f"{bad}: {value!r} is not one of {', '.join(entries)}")
            if name == "PixelFormat":
                pixel_format_info(value)
            return value
        if kind == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise CameraError(f"{bad}: expects a boolean, got {value!r}")
            return bool(value)
        if kind == "str":
            if not isinstance(value, str) or not value.isprintable():
                raise CameraError(f"{bad}: expects printable text, got {value!r}")
            return value
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
            raise CameraError(f"{bad}: expects a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise CameraError(f"{bad}: {value!r} is not a finite number")
        lo, hi = self.feature_range(name)
        if kind == "int":
            if float(value) != int(value):
                raise CameraError(f"{bad}: expects an integer, got {value!r}")
            value = int(value)
            inc = self._device_call(f"read {name} increment", cam.get_integer_increment, name)
            if inc > 1 and (value - lo) % inc:
                raise CameraError(f"{bad}: {value} is not {lo} + a multiple of {inc}")
        else:
            value = float(value)
        if not lo <= value <= hi:
            raise CameraError(f"{bad}: {value!r} is outside [{lo}, {hi}]")
        return value

    def _write(self, name: str, value) -> None:
        cam = self._require_open()
        kind = self._kind(name)
        setter = getattr(cam, f"set_{_ACCESSORS[kind]}")
        self._device_call(f"write {name} = {value!r}", setter, name, value)

    # -- acquisition --------------------------------------------------------------------

    def start(self, n_buffers: int = 16) -> None:
        """Allocate `n_buffers` frame buffers and start the acquisition.

        Raises
        ------
        CameraError
            If the camera is not open, the stream cannot be created or the start fails.
        """
        Aravis, _ = _aravis()
        cam = self._require_open()
        if self._stream is not None:
            return
        if not isinstance(n_buffers, numbers.Integral) or not 1 <= n_buffers <= 1024:
            raise CameraError(f"{self._label}: n_buffers {n_buffers!r} outside 1..1024")
        pixel_format_info(self.get("PixelFormat"))
        stream = self._device_call("create stream", cam.create_stream, None, None)
        if stream is None:
            raise CameraError(f"{self._label}: cannot create a stream")
        payload = self._device_call("read payload size", cam.get_payload)
        for _ in range(n_buffers):
            stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self._device_call(
            "set acquisition mode", cam.set_acquisition_mode, Aravis.AcquisitionMode.CONTINUOUS
        )
        self._stream, self._n_buffers = stream, int(n_buffers)
        self._want_acquiring = True
        try:
            self._device_call("start acquisition", cam.start_acquisition)
        except CameraError:
            self._stream = None
            raise

    def stop(self) -> None:
        """Stop the acquisition and release the buffers (safe when not acquiring)."""
        self._want_acquiring = False
        if self._stream is None:
            return
        stream, self._stream = self._stream, None
        self._add_stats(stream)
        try:
            self._device_call("stop acquisition", self._cam.stop_acquisition)
        except CameraError:
            pass  # a lost device has stopped anyway; `error` says so

    def software_trigger(self) -> None:
        """Execute ``TriggerSoftware`` (the camera must be in TriggerMode On, source Software)."""
        cam = self._require_open()
        self._device_call("TriggerSoftware", cam.software_trigger)

    def grab(self, timeout_s: float) -> CameraFrame | None:
        """The next complete frame, or None if none arrives within `timeout_s` [s].

        Incomplete buffers (lost packets) are skipped; `statistics` counts them.
        """
        Aravis, _ = _aravis()
        if self._stream is None:
            raise CameraError(f"{self._label}: not acquiring (call start first)")
        if not (
            isinstance(timeout_s, numbers.Real) and math.isfinite(timeout_s) and timeout_s >= 0
        ):
            raise CameraError(
                f"{self._label}: grab timeout {timeout_s!r} must be a finite number >= 0 s"
            )
        stream = self._stream
        deadline = time.monotonic() + float(timeout_s)
        while True:
            left_us = max(0, int((deadline - time.monotonic()) * 1e6))
            buf = stream.timeout_pop_buffer(left_us)
            if buf is None:
                return None
            try:
                if buf.get_status() == Aravis.BufferStatus.SUCCESS:
                    return self._frame(buf)
            finally:
                stream.push_buffer(buf)
            if time.monotonic() >= deadline:
                return None

    def _frame(self, buf) -> CameraFrame:
        pfnc = buf.get_image_pixel_format()
        depth = _BIT_DEPTH_BY_PFNC.get(pfnc)
        if depth is None:
            raise CameraError(f"{self._label}: frame in unsupported pixel format 0x{pfnc:08x}")
        h, w = buf.get_image_height(), buf.get_image_width()
        dtype = np.uint8 if depth == 8 else np.dtype("<u2")
        data = buf.get_image_data()
        image = np.frombuffer(data, dtype=dtype, count=h * w).reshape(h, w)
        return CameraFrame(
            image=image,
            frame_id=int(buf.get_frame_id()),
            timestamp_ns=int(buf.get_timestamp()),
            bit_depth=depth,
        )

    def _add_stats(self, stream) -> None:
        done, failed, underrun = _aravis()[0].Stream.get_statistics(stream)
        self._stats_before = {
            "completed": self._stats_before["completed"] + done,
            "failed": self._stats_before["failed"] + failed,
            "underrun": self._stats_before["underrun"] + underrun,
        }

    def statistics(self) -> dict:
        """Buffers since this object was made, across stops and reopens.

        Returns
        -------
        dict
            ``completed`` (complete frames received), ``failed`` (incomplete: lost packets,
            timeouts), ``underrun`` (frames lost because no buffer was free).
        """
        stats = dict(self._stats_before)
        if self._stream is not None:
            done, failed, underrun = _aravis()[0].Stream.get_statistics(self._stream)
            stats["completed"] += done
            stats["failed"] += failed
            stats["underrun"] += underrun
        return stats


def main(argv: list[str] | None = None) -> int:
    """Print the cameras Aravis can see, one line each."""
    cams = list_cameras()
    for c in cams:
        print(
            f"{c['id']}\tserial {c['serial']}\t{c['vendor']} {c['model']}\t"
            f"{c['protocol']} {c['address']}"
        )
    if not cams:
        print("no camera found", file=sys.stderr)
    return 0 if cams else 1


if __name__ == "__main__":
    sys.exit(main())
