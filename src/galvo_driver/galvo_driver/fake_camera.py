"""A simulated GenICam camera for tests and benchmarks: Aravis' GigE Vision fake camera.

`FakeCamera` runs ``python -m galvo_driver.fake_camera`` as a child process. The child
creates Aravis' ``ArvGvFakeCamera`` on the loopback interface: a GigE Vision device that
answers real GVCP (discovery, register reads/writes, the GenICam XML download) and streams
real GVSP packets, so a client reaches it exactly as it reaches a camera on a network.
"Unplugging" it is killing the child; "replugging" is starting it again with the same
serial number.

The GenICam description it serves is `GENICAM_XML` below, written for this project with
the standard feature names (SFNC) a real camera uses: ``ExposureTime`` [us], ``Gain``,
``PixelFormat`` (``Mono8``, ``Mono16``), ``Width``/``Height``/``OffsetX``/``OffsetY``,
``AcquisitionFrameRate`` [Hz], ``TriggerSelector``/``TriggerMode``/``TriggerSource``/
``TriggerActivation``/``TriggerSoftware``, ``DeviceUserID``. Its registers are the ones
Aravis' fake camera acts on; the image is Aravis' diagonal ramp, shifted by one grey level
per frame. What the fake camera cannot do, and the description therefore does not offer:
``Mono10``/``Mono12`` (it renders only 8- and 16-bit mono).

Trigger line: ``TriggerSource`` ``Line0`` is the camera's trigger input. Its wire is a UDP
port on loopback (`FakeCamera.line_port`): every datagram is a rising edge
(`FakeCamera.pulse_line`), taken only while ``TriggerMode`` is ``On`` and ``TriggerSource``
is ``Line0``, as a real camera ignores its line in any other mode. So a trigger source in
another process (the galvo board's emulator) fires the camera as the board's trigger output
fires a real one, while the driver alone controls the camera over GVCP. The datagram
carries the edge's instant (CLOCK_REALTIME, ns), and a frame exposed by a line edge is
stamped with it, as a camera latches its timestamp at the exposure start in hardware: the
frame itself still comes when the fake camera's thread gets to it (a loaded machine delays
it), and an edge that comes while the previous one is still pending is ignored (the camera
misses that trigger, as a busy camera does). ``TriggerSoftware`` fires the camera whatever
the source (a real camera would ignore it under ``Line0``); such frames keep Aravis' stamp
(the time the frame is made). The first 8 bytes of a line-triggered ramp image carry the
edge's instant too (little-endian ns, `edge_of`): the truth a test traces every frame back to the
trigger that exposed it with, whatever the driver made of it.

Triggered frames are produced on a time grid: the fake camera looks for a pending
software trigger every ``1 / trigger_frequency_hz`` seconds, so two triggers within one
slot give one frame (as a real camera ignores an overlapping trigger). The default slot
is 0.25 ms (4 kHz), which leaves a 500 fps trigger stream one frame per trigger; the
price is that the child busy-polls one CPU core while acquiring in trigger mode. (Aravis
0.8's streaming thread can oversleep a slot by 100 ms; a line edge wakes it, see
``_serve``. Until the first frame of an acquisition it looks for a trigger only every
100 ms, so the edges of the first ~100 ms after AcquisitionStart may give a single frame.)

Only one fake camera can serve on the loopback interface at a time (GVCP port 3956).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time

# Registers of Aravis' fake camera (arvfakecamera.h) and the GigE Vision bootstrap.
_REG_SENSOR_WIDTH = 0x11C
_REG_SENSOR_HEIGHT = 0x118
_REG_WIDTH = 0x100
_REG_HEIGHT = 0x104
_REG_EXPOSURE_US = 0x120
_REG_FRAME_PERIOD_US = 0x138
_REG_ACQUISITION = 0x124
_REG_OFFSET_X = 0x130
_REG_OFFSET_Y = 0x134
_REG_PIXEL_FORMAT = 0x128
_REG_TRIGGER_MODE = 0x300
# Aravis' own trigger-source register: kept at 1 (software) so that the fake camera takes
# a trigger whenever TriggerSoftware is set; the source a client selects lives in
# _REG_TRIGGER_SOURCE_SELECTED (0 = Line0, 1 = Software), which the line honours.
_REG_ARAVIS_TRIGGER_SOURCE = 0x304
_REG_TRIGGER_SOFTWARE = 0x30C
_REG_TRIGGER_SOURCE_SELECTED = 0x310
_GVBS_USER_DEFINED_NAME = 0xE8
_GVBS_USER_DEFINED_NAME_SIZE = 16
_READY = "FAKE_CAMERA_READY"
#: The child's answer to a scene change (render cameras): "FAKE_CAMERA_SCENE ok <n>" or
#: "FAKE_CAMERA_SCENE error <message>".
_SCENE = "FAKE_CAMERA_SCENE"
#: The child's last stderr line: what became of the line's edges, and the frames it made
_LINE_REPORT = "FAKE_CAMERA_LINE"
_GVCP_PORT = 3956
# A GVCP READREG command (key 0x42, flags, command 0x0080, length 4, request id, address)
# of the bootstrap version register: harmless, answered by any GigE Vision device.
_GVCP_WAKE = struct.pack(">BBHHHI", 0x42, 0x01, 0x0080, 4, 1, 0x0000)
_WAKE_PERIOD_S = 0.0005

GENICAM_XML = """<?xml version="1.0" encoding="utf-8"?>
<RegisterDescription ModelName="GalvoscanFake" VendorName="Aravis"
  StandardNameSpace="None" SchemaMajorVersion="1" SchemaMinorVersion="0"
  SchemaSubMinorVersion="1" MajorVersion="1" MinorVersion="0" SubMinorVersion="0"
  ToolTip="galvoscan simulated camera (Aravis GigE Vision fake camera)"
  ProductGuid="0" VersionGuid="0"
  xmlns="http://www.genicam.org/GenApi/Version_1_0"
  xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
  xsi:schemaLocation="http://www.genicam.org/GenApi/Version_1_0 GenApiSchema.xsd">
  <Category Name="Root" NameSpace="Standard">
    <pFeature>DeviceControl</pFeature>
    <pFeature>ImageFormatControl</pFeature>
    <pFeature>AcquisitionControl</pFeature>
    <pFeature>AnalogControl</pFeature>
    <pFeature>TransportLayerControl</pFeature>
  </Category>
  <Category Name="DeviceControl" NameSpace="Standard">
    <pFeature>DeviceVendorName</pFeature>
    <pFeature>DeviceModelName</pFeature>
    <pFeature>DeviceSerialNumber</pFeature>
    <pFeature>DeviceUserID</pFeature>
  </Category>
  <StringReg Name="DeviceVendorName" NameSpace="Standard">
    <Address>0x48</Address><Length>32</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>
  <StringReg Name="DeviceModelName" NameSpace="Standard">
    <Address>0x68</Address><Length>32</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>
  <StringReg Name="DeviceSerialNumber" NameSpace="Standard">
    <Address>0xd8</Address><Length>16</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
  </StringReg>
  <StringReg Name="DeviceUserID" NameSpace="Standard">
    <Address>0xe8</Address><Length>16</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
  </StringReg>
  <Category Name="ImageFormatControl" NameSpace="Standard">
    <pFeature>SensorWidth</pFeature>
    <pFeature>SensorHeight</pFeature>
    <pFeature>Width</pFeature>
    <pFeature>Height</pFeature>
    <pFeature>OffsetX</pFeature>
    <pFeature>OffsetY</pFeature>
    <pFeature>PixelFormat</pFeature>
  </Category>
  <Integer Name="SensorWidth" NameSpace="Standard">
    <pValue>SensorWidthRegister</pValue>
  </Integer>
  <IntReg Name="SensorWidthRegister" NameSpace="Custom">
    <Address>0x11c</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Integer Name="SensorHeight" NameSpace="Standard">
    <pValue>SensorHeightRegister</pValue>
  </Integer>
  <IntReg Name="SensorHeightRegister" NameSpace="Custom">
    <Address>0x118</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Integer Name="Width" NameSpace="Standard">
    <pValue>WidthRegister</pValue><Min>16</Min><pMax>WidthMax</pMax><Inc>1</Inc>
  </Integer>
  <IntSwissKnife Name="WidthMax" NameSpace="Custom">
    <pVariable Name="SENSOR">SensorWidth</pVariable>
    <pVariable Name="OFFSET">OffsetX</pVariable>
    <Formula>SENSOR - OFFSET</Formula>
  </IntSwissKnife>
  <IntReg Name="WidthRegister" NameSpace="Custom">
    <Address>0x100</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Integer Name="Height" NameSpace="Standard">
    <pValue>HeightRegister</pValue><Min>16</Min><pMax>HeightMax</pMax><Inc>1</Inc>
  </Integer>
  <IntSwissKnife Name="HeightMax" NameSpace="Custom">
    <pVariable Name="SENSOR">SensorHeight</pVariable>
    <pVariable Name="OFFSET">OffsetY</pVariable>
    <Formula>SENSOR - OFFSET</Formula>
  </IntSwissKnife>
  <IntReg Name="HeightRegister" NameSpace="Custom">
    <Address>0x104</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Integer Name="OffsetX" NameSpace="Standard">
    <pValue>OffsetXRegister</pValue><Min>0</Min><pMax>OffsetXMax</pMax><Inc>1</Inc>
  </Integer>
  <IntSwissKnife Name="OffsetXMax" NameSpace="Custom">
    <pVariable Name="SENSOR">SensorWidth</pVariable>
    <pVariable Name="SIZE">WidthRegister</pVariable>
    <Formula>SENSOR - SIZE</Formula>
  </IntSwissKnife>
  <IntReg Name="OffsetXRegister" NameSpace="Custom">
    <Address>0x130</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Integer Name="OffsetY" NameSpace="Standard">
    <pValue>OffsetYRegister</pValue><Min>0</Min><pMax>OffsetYMax</pMax><Inc>1</Inc>
  </Integer>
  <IntSwissKnife Name="OffsetYMax" NameSpace="Custom">
    <pVariable Name="SENSOR">SensorHeight</pVariable>
    <pVariable Name="SIZE">HeightRegister</pVariable>
    <Formula>SENSOR - SIZE</Formula>
  </IntSwissKnife>
  <IntReg Name="OffsetYRegister" NameSpace="Custom">
    <Address>0x134</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Enumeration Name="PixelFormat" NameSpace="Standard">
    <EnumEntry Name="Mono8" NameSpace="Standard"><Value>17301505</Value></EnumEntry>
    <EnumEntry Name="Mono12" NameSpace="Standard"><Value>17825797</Value></EnumEntry>
    <EnumEntry Name="Mono16" NameSpace="Standard"><Value>17825799</Value></EnumEntry>
    <pValue>PixelFormatRegister</pValue>
  </Enumeration>
  <IntReg Name="PixelFormatRegister" NameSpace="Custom">
    <Address>0x128</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Category Name="AcquisitionControl" NameSpace="Standard">
    <pFeature>AcquisitionMode</pFeature>
    <pFeature>AcquisitionStart</pFeature>
    <pFeature>AcquisitionStop</pFeature>
    <pFeature>AcquisitionFrameRate</pFeature>
    <pFeature>TriggerSelector</pFeature>
    <pFeature>TriggerMode</pFeature>
    <pFeature>TriggerSource</pFeature>
    <pFeature>TriggerActivation</pFeature>
    <pFeature>TriggerSoftware</pFeature>
    <pFeature>ExposureTime</pFeature>
  </Category>
  <Enumeration Name="AcquisitionMode" NameSpace="Standard">
    <EnumEntry Name="Continuous" NameSpace="Standard"><Value>1</Value></EnumEntry>
    <pValue>AcquisitionModeRegister</pValue>
  </Enumeration>
  <IntReg Name="AcquisitionModeRegister" NameSpace="Custom">
    <Address>0x12c</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Command Name="AcquisitionStart" NameSpace="Standard">
    <pValue>AcquisitionCommandRegister</pValue><CommandValue>1</CommandValue>
  </Command>
  <Command Name="AcquisitionStop" NameSpace="Standard">
    <pValue>AcquisitionCommandRegister</pValue><CommandValue>0</CommandValue>
  </Command>
  <IntReg Name="AcquisitionCommandRegister" NameSpace="Custom">
    <Address>0x124</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Float Name="AcquisitionFrameRate" NameSpace="Standard">
    <pValue>AcquisitionFrameRateConverter</pValue><Min>1.0</Min><Max>1000.0</Max>
    <Unit>Hz</Unit>
  </Float>
  <Converter Name="AcquisitionFrameRateConverter" NameSpace="Custom">
    <FormulaTo>(1000000 / FROM)</FormulaTo>
    <FormulaFrom>(1000000 / TO)</FormulaFrom>
    <pValue>AcquisitionFramePeriodRegister</pValue>
  </Converter>
  <IntReg Name="AcquisitionFramePeriodRegister" NameSpace="Custom">
    <Address>0x138</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Enumeration Name="TriggerSelector" NameSpace="Standard">
    <EnumEntry Name="FrameStart" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <pValue>TriggerSelectorInteger</pValue>
  </Enumeration>
  <Integer Name="TriggerSelectorInteger" NameSpace="Custom">
    <Value>0</Value>
  </Integer>
  <Enumeration Name="TriggerMode" NameSpace="Standard">
    <EnumEntry Name="Off" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <EnumEntry Name="On" NameSpace="Standard"><Value>1</Value></EnumEntry>
    <pValue>TriggerModeRegister</pValue>
  </Enumeration>
  <IntReg Name="TriggerModeRegister" NameSpace="Custom">
    <Address>0x300</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Enumeration Name="TriggerSource" NameSpace="Standard">
    <EnumEntry Name="Line0" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <EnumEntry Name="Software" NameSpace="Standard"><Value>1</Value></EnumEntry>
    <pValue>TriggerSourceRegister</pValue>
  </Enumeration>
  <IntReg Name="TriggerSourceRegister" NameSpace="Custom">
    <Address>0x310</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Enumeration Name="TriggerActivation" NameSpace="Standard">
    <EnumEntry Name="RisingEdge" NameSpace="Standard"><Value>0</Value></EnumEntry>
    <EnumEntry Name="FallingEdge" NameSpace="Standard"><Value>1</Value></EnumEntry>
    <pValue>TriggerActivationRegister</pValue>
  </Enumeration>
  <IntReg Name="TriggerActivationRegister" NameSpace="Custom">
    <Address>0x308</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Command Name="TriggerSoftware" NameSpace="Standard">
    <pValue>TriggerSoftwareCommandRegister</pValue><CommandValue>1</CommandValue>
  </Command>
  <IntReg Name="TriggerSoftwareCommandRegister" NameSpace="Custom">
    <Address>0x30c</Address><Length>4</Length><AccessMode>WO</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Float Name="ExposureTime" NameSpace="Standard">
    <pValue>ExposureTimeConverter</pValue><Min>10.0</Min><Max>1000000.0</Max><Unit>us</Unit>
  </Float>
  <Converter Name="ExposureTimeConverter" NameSpace="Custom">
    <FormulaTo>FROM</FormulaTo>
    <FormulaFrom>TO</FormulaFrom>
    <pValue>ExposureTimeRegister</pValue>
  </Converter>
  <IntReg Name="ExposureTimeRegister" NameSpace="Custom">
    <Address>0x120</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Category Name="AnalogControl" NameSpace="Standard">
    <pFeature>Gain</pFeature>
  </Category>
  <Float Name="Gain" NameSpace="Standard">
    <pValue>GainConverter</pValue><Min>0.0</Min><Max>10.0</Max>
  </Float>
  <Converter Name="GainConverter" NameSpace="Custom">
    <FormulaTo>FROM</FormulaTo>
    <FormulaFrom>TO</FormulaFrom>
    <pValue>GainRegister</pValue>
  </Converter>
  <IntReg Name="GainRegister" NameSpace="Custom">
    <Address>0x110</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort>
    <Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
  </IntReg>
  <Category Name="TransportLayerControl" NameSpace="Standard">
    <pFeature>PayloadSize</pFeature>
  </Category>
  <IntSwissKnife Name="PayloadSize" NameSpace="Standard">
    <pVariable Name="WIDTH">Width</pVariable>
    <pVariable Name="HEIGHT">Height</pVariable>
    <pVariable Name="PIXELFORMAT">PixelFormat</pVariable>
    <Formula>WIDTH * HEIGHT * ((PIXELFORMAT&gt;&gt;16)&amp;0xFF) / 8</Formula>
  </IntSwissKnife>
  <Integer Name="TLParamsLocked">
    <Visibility>Invisible</Visibility><Value>0</Value><Min>0</Min><Max>1</Max>
  </Integer>
  <Port Name="Device" NameSpace="Standard"/>
</RegisterDescription>
"""


class FakeCamera:
    """A simulated GigE Vision camera on loopback, run as a child process.

    Parameters
    ----------
    serial : str
        Serial number the camera reports (at most 15 characters).
    width, height : int
        Sensor size [px]; the region of interest starts as the full sensor.
    user_id : str, optional
        DeviceUserID the camera reports (at most 15 characters); ``None`` leaves it empty.
    trigger_frequency_hz : float
        How often the fake camera looks for a pending software trigger [Hz] (see the
        module's docstring).
    start_timeout_s : float
        How long `replug` waits for the camera to answer discovery [s].
    wake_on_edge : bool
        Wake Aravis' streaming thread with a GVCP register read on each line edge and while
        its trigger is pending (see ``_serve``): the camera then makes a frame for nearly
        every edge at 500 Hz, at the price of GVCP traffic beside the client's and more CPU
        (``benchmarks/camera_trigger.py`` uses it). Off, it misses edges as Aravis does.
    render : dict, optional
        Make the camera a simulated rig's camera (:mod:`galvo_driver.twin`): each line edge
        datagram carries the DAC outputs and laser level at the edge (the harness's
        ``--edge-udp``, :data:`~galvo_driver.serial_link.simavr_board.EDGE_FORMAT`), and the
        image of that edge is the simulator's exposure of the scene at those outputs
        (:class:`~galvo_driver.twin_render.Renderer`) instead of the ramp. Keys: ``rig``,
        ``scene``, ``seed`` and ``log`` (a file where each rendered frame's edge, codes
        and image CRC are written). The scene is changed with `set_scene`. The sensor
        size is the rig's (``width``/``height`` are ignored).

    Use it as a context manager: it starts on entry and is stopped on exit.
    """

    def __init__(
        self,
        serial: str = "GSFAKE0",
        width: int = 720,
        height: int = 540,
        user_id: str | None = None,
        trigger_frequency_hz: float = 4000.0,
        start_timeout_s: float = 10.0,
        wake_on_edge: bool = False,
        render: dict | None = None,
    ):
        for name, text in (("serial", serial), ("user_id", user_id or "")):
            if len(text.encode()) >= _GVBS_USER_DEFINED_NAME_SIZE or not text.isprintable():
                raise ValueError(
                    f"FakeCamera: {name} {text!r} must be printable and at most 15 bytes"
                )
        if not serial:
            raise ValueError("FakeCamera: serial must not be empty")
        if not (16 <= int(width) <= 8192 and 16 <= int(height) <= 8192):
            raise ValueError(f"FakeCamera: sensor {width}x{height} px outside 16..8192")
        if not (1.0 <= float(trigger_frequency_hz) <= 100_000.0):
            raise ValueError(
                f"FakeCamera: trigger_frequency_hz {trigger_frequency_hz} outside 1..1e5"
            )
        self.serial = serial
        self.user_id = user_id
        self.width = int(width)
        self.height = int(height)
        self.trigger_frequency_hz = float(trigger_frequency_hz)
        self.start_timeout_s = float(start_timeout_s)
        self.wake_on_edge = bool(wake_on_edge)
        self.render = dict(render) if render else None
        if self.render is not None:
            unknown = sorted(set(self.render) - {"rig", "scene", "seed", "log"})
            if unknown or "rig" not in self.render:
                raise ValueError(f"FakeCamera: render needs 'rig' (and may have 'scene', "
                                 f"'seed', 'log'); unknown {unknown}")
        self._ctl_lock = threading.Lock()
        self._proc: subprocess.Popen | None = None
        self._xml_dir: tempfile.TemporaryDirectory | None = None
        self._line_port: int | None = None
        self._line_sock: socket.socket | None = None
        #: After `close`: the child's count of line edges (``edges``, ``taken``, ``missed
        #: (previous trigger pending)``, ``ignored (not the trigger source)``) and
        #: ``frames made``; empty before.
        self.line_report: dict = {}

    # -- life cycle ---------------------------------------------------------------------

    def __enter__(self) -> FakeCamera:
        self.replug()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def running(self) -> bool:
        """Whether the camera process is alive."""
        return self._proc is not None and self._proc.poll() is None

    def replug(self) -> None:
        """Start the camera (again, with the same serial) and wait until it is discoverable.

        Raises
        ------
        RuntimeError
            If the child process exits or is not discoverable within ``start_timeout_s``.
        """
        if self.running:
            return
        if self._xml_dir is None:
            self._xml_dir = tempfile.TemporaryDirectory(prefix="galvoscan-fakecam-")
        xml_path = os.path.join(self._xml_dir.name, "galvoscan-fake-camera.xml")
        with open(xml_path, "w", encoding="utf-8") as f:
            f.write(GENICAM_XML)
        cmd = [
            sys.executable,
            "-m",
            "galvo_driver.fake_camera",
            "--serial",
            self.serial,
            "--width",
            str(self.width),
            "--height",
            str(self.height),
            "--trigger-frequency",
            repr(self.trigger_frequency_hz),
            "--genicam",
            xml_path,
        ]
        if self.user_id:
            cmd += ["--user-id", self.user_id]
        if self.wake_on_edge:
            cmd += ["--wake-on-edge"]
        if self.render is not None:
            cmd += ["--render", json.dumps(self.render)]
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        deadline = time.monotonic() + self.start_timeout_s
        if not self._wait_ready(deadline):
            err = self._stop(signal.SIGKILL)
            raise RuntimeError(f"FakeCamera {self.serial}: the fake camera did not start: {err}")
        if not self._wait_discoverable(deadline):
            self._stop(signal.SIGKILL)
            raise RuntimeError(
                f"FakeCamera {self.serial}: not discoverable on loopback within "
                f"{self.start_timeout_s} s (another fake camera on GVCP port 3956?)"
            )

    def set_scene(self, text: str, timeout: float = 30.0) -> int:
        """Replace the rendered scene (``render`` cameras) with simulator scene YAML;
        returns its number of objects.

        Raises
        ------
        ValueError
            The scene is malformed (the camera keeps the scene it had).
        RuntimeError
            Not a rendering camera, not running, or no answer within ``timeout`` [s].
        """
        if self.render is None:
            raise RuntimeError(f"FakeCamera {self.serial}: not a rendering camera")
        data = str(text).encode("utf-8")
        with self._ctl_lock:
            if not self.running:
                raise RuntimeError(f"FakeCamera {self.serial}: not running")
            assert self._proc is not None and self._proc.stdin and self._proc.stdout
            try:
                self._proc.stdin.write(f"scene {len(data)}\n")
                self._proc.stdin.flush()
                self._proc.stdin.buffer.write(data)
                self._proc.stdin.buffer.flush()
            except (BrokenPipeError, OSError) as err:
                raise RuntimeError(f"FakeCamera {self.serial}: {err}") from err
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                ready, _, _ = select.select([self._proc.stdout], [], [], 0.1)
                if not ready:
                    if not self.running:
                        break
                    continue
                line = self._proc.stdout.readline()
                if not line:
                    break
                words = line.rstrip("\n").split(" ", 2)
                if words[0] != _SCENE:
                    continue
                if words[1] == "ok":
                    return int(words[2])
                raise ValueError(words[2] if len(words) > 2 else "scene refused")
        raise RuntimeError(f"FakeCamera {self.serial}: no answer to the scene change")

    def unplug(self) -> None:
        """Cut the camera off as a pulled cable or power loss would: SIGKILL the process."""
        self._stop(signal.SIGKILL)

    @property
    def line_port(self) -> int | None:
        """UDP port on 127.0.0.1 of the camera's trigger input ``Line0`` (None while the
        camera is not running); it changes with every `replug`."""
        return self._line_port if self.running else None

    def pulse_line(self, t_ns: int | None = None) -> None:
        """One rising edge on the trigger input ``Line0`` (a datagram to `line_port`).

        Cheap enough to call from the board emulator's trigger hook. A pulse while the
        camera is unplugged goes nowhere, as on a wire to a dead camera.

        Parameters
        ----------
        t_ns : int, optional
            The edge's instant, CLOCK_REALTIME [ns]; default: now.
        """
        port = self._line_port
        if port is None:
            return
        if self._line_sock is None:
            self._line_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        edge = time.time_ns() if t_ns is None else int(t_ns)
        try:
            self._line_sock.sendto(edge.to_bytes(8, "little"), ("127.0.0.1", port))
        except OSError:
            pass  # nobody listens (the camera was killed): the edge is lost

    def close(self) -> None:
        """Stop the camera and remove its temporary files. What became of the line's
        edges is then in `line_report`."""
        err = self._stop(signal.SIGTERM)
        for line in err.splitlines():
            if line.startswith(_LINE_REPORT + " "):
                try:
                    self.line_report = json.loads(line[len(_LINE_REPORT) + 1:])
                except ValueError:
                    pass
        if self._line_sock is not None:
            self._line_sock.close()
            self._line_sock = None
        if self._xml_dir is not None:
            self._xml_dir.cleanup()
            self._xml_dir = None

    # -- helpers ------------------------------------------------------------------------

    def _wait_ready(self, deadline: float) -> bool:
        assert self._proc is not None and self._proc.stdout is not None
        while time.monotonic() < deadline:
            ready, _, _ = select.select([self._proc.stdout], [], [], 0.1)
            if ready:
                line = self._proc.stdout.readline()
                words = line.split()
                if words[:1] == [_READY] and len(words) == 2:
                    self._line_port = int(words[1])
                    return True
                if not line:
                    return False
            if self._proc.poll() is not None:
                return False
        return False

    def _wait_discoverable(self, deadline: float) -> bool:
        from galvo_driver.genicam_camera import list_cameras

        while time.monotonic() < deadline:
            if any(c["serial"] == self.serial for c in list_cameras()):
                return True
            if not self.running:
                return False
        return False

    def _stop(self, sig: int) -> str:
        """Stop the child with `sig`; return what it wrote on stderr."""
        proc, self._proc = self._proc, None
        self._line_port = None
        if proc is None:
            return ""
        if proc.poll() is None:
            proc.send_signal(sig)
        try:
            _, err = proc.communicate(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        return (err or "").strip()[-2000:]


def edge_at(t_monotonic: float) -> int:
    """The CLOCK_REALTIME instant [ns] of a line edge that happened at ``t_monotonic``.

    The board emulator's trigger hook runs in a thread of the caller's process, which may
    be scheduled late (a garbage collection, another thread holding the GIL); an edge
    stamped "now" in the hook would carry that delay, which a wire does not. Give
    `FakeCamera.pulse_line` the trigger's own instant instead.

    Parameters
    ----------
    t_monotonic : float
        ``time.monotonic()`` of the edge [s] (the emulator's trigger instant).
    """
    return round(t_monotonic * 1e9) + (time.time_ns() - time.monotonic_ns())


def edge_of(image) -> int | None:
    """The line edge instant [ns, CLOCK_REALTIME] a fake-camera image was exposed by.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8 or uint16
        An image of a frame the fake camera made for a ``Line0`` edge.

    Returns
    -------
    int or None
        The instant `FakeCamera.pulse_line` sent; None for an image too small to carry it.
    """
    import numpy as np

    raw = np.ascontiguousarray(image).reshape(-1).view(np.uint8)
    return int.from_bytes(raw[:8].tobytes(), "little") if raw.size >= 8 else None


class _Fill:
    """A fill for Aravis' fake camera: the callback that writes each frame's image.

    Registered through ctypes (the GObject binding of this callback is scope "call" and
    cannot outlive the call that registers it); it runs on the fake camera's streaming
    thread. Subclasses write the image in :meth:`_fill`.
    """

    def __init__(self):
        import ctypes

        self._ct = ctypes
        lib = ctypes.CDLL("libaravis-0.8.so.0")
        lib.arv_buffer_get_data.restype = ctypes.c_void_p
        lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
        for fn in ("arv_buffer_get_image_width", "arv_buffer_get_image_height"):
            getattr(lib, fn).restype = ctypes.c_int
            getattr(lib, fn).argtypes = [ctypes.c_void_p]
        lib.arv_buffer_get_frame_id.restype = ctypes.c_uint64
        lib.arv_buffer_get_frame_id.argtypes = [ctypes.c_void_p]
        lib.arv_buffer_set_timestamp.restype = None
        lib.arv_buffer_set_timestamp.argtypes = [ctypes.c_void_p, ctypes.c_uint64]
        #: Frames filled (made by the streaming thread), line-triggered or not.
        self.frames = 0
        self._proto = ctypes.CFUNCTYPE(
            None,
            ctypes.c_void_p,
            ctypes.c_void_p,
            ctypes.c_uint32,
            ctypes.c_uint32,
            ctypes.c_uint32,
        )
        lib.arv_fake_camera_set_fill_pattern.restype = None
        lib.arv_fake_camera_set_fill_pattern.argtypes = [
            ctypes.c_void_p,
            self._proto,
            ctypes.c_void_p,
        ]
        self._lib = lib
        self._callback = self._proto(self._fill)  # kept alive as long as this object

    def install(self, fake_camera) -> None:
        """Make `fake_camera` (an Aravis.FakeCamera) call this fill for every frame."""
        # PyGObject's hash of a GObject wrapper is the address of the C object.
        self._lib.arv_fake_camera_set_fill_pattern(hash(fake_camera), self._callback, None)

    def _dest(self, buffer, item: int):
        """(width, height, the buffer's bytes as a uint8 array) of an Aravis buffer."""
        import numpy as np

        lib = self._lib
        w = lib.arv_buffer_get_image_width(buffer)
        h = lib.arv_buffer_get_image_height(buffer)
        size = self._ct.c_size_t(0)  # the received size: not yet set while filling
        addr = lib.arv_buffer_get_data(buffer, self._ct.byref(size))
        return w, h, np.ctypeslib.as_array((self._ct.c_uint8 * (w * h * item)).from_address(addr))

    def _fill(self, buffer, _data, exposure_us, gain, pixel_format) -> None:
        raise NotImplementedError


class _ImageFill(_Fill):
    """Frames whose images are given: each line edge taken queues (edge instant, image),
    and the next frame the streaming thread makes carries that image as it is, stamped with
    the edge (exposure start). An image that does not fit the buffer (the region of interest
    or the pixel format changed since it was made), and a frame without a queued image (a
    software trigger), are sent black.
    """

    def __init__(self):
        super().__init__()
        #: (edge instant [ns], image ndarray) of the edges taken and not yet sent.
        self.images: collections.deque = collections.deque()

    def _fill(self, buffer, _data, exposure_us, gain, pixel_format) -> None:
        import numpy as np

        self.frames += 1
        item = self.images.popleft() if self.images else None
        depth = _PIXEL_DEPTH.get(int(pixel_format), 8)
        nbytes = 1 if depth == 8 else 2
        w, h, dest = self._dest(buffer, nbytes)
        if item is None:
            dest[:] = 0
            return
        edge, image = item
        self._lib.arv_buffer_set_timestamp(buffer, edge)
        if image.shape == (h, w) and image.itemsize == nbytes and dest.size == image.nbytes:
            np.copyto(dest, np.ascontiguousarray(image).reshape(-1).view(np.uint8))
        else:
            dest[:] = 0


#: Bits per pixel of the pixel formats the fake camera renders (PFNC codes).
_PIXEL_DEPTH = {0x01080001: 8, 0x01100005: 12, 0x01100007: 16}


class _RampFill(_Fill):
    """The image the fake camera sends: a diagonal ramp moving one grey level per frame.

    Pixel (y, x) of frame f is ``((x + y + f) % 255) * scale`` in 8 bits (x16 for Mono12,
    x256 for Mono16), clamped, with ``scale = (1 + Gain) * ExposureTime / 10 ms``. It
    replaces Aravis' own pattern, which spends ~5 ms per 720x540 frame and so caps the
    camera near 200 fps.
    """

    def __init__(self):
        super().__init__()
        #: Instants [ns] of the line edges taken and not yet turned into a frame, oldest first.
        self.edges: collections.deque = collections.deque()
        self._ramps: dict[tuple, object] = {}

    def _ramp(self, exposure_us: int, gain: int, pixel_format: int, length: int):
        import numpy as np

        key = (exposure_us, gain, pixel_format, length)
        ramp = self._ramps.get(key)
        if ramp is None:
            depth = {0x01080001: 8, 0x01100005: 12, 0x01100007: 16}.get(pixel_format)
            if depth is None:
                return None
            scale = (1.0 + gain) * exposure_us / 10_000.0
            top = (1 << depth) - 1
            level = (np.arange(length) % 255) * (1 << (depth - 8)) * scale
            ramp = np.clip(np.rint(level), 0, top).astype(np.uint8 if depth == 8 else "<u2")
            if len(self._ramps) > 64:
                self._ramps.clear()
            self._ramps[key] = ramp
        return ramp

    def _fill(self, buffer, _data, exposure_us, gain, pixel_format) -> None:
        import numpy as np

        lib = self._lib
        self.frames += 1
        edge = self.edges.popleft() if self.edges else None
        if edge is not None:  # a frame of a line edge: stamped with the edge (exposure start)
            lib.arv_buffer_set_timestamp(buffer, edge)
        w = lib.arv_buffer_get_image_width(buffer)
        h = lib.arv_buffer_get_image_height(buffer)
        f = int(lib.arv_buffer_get_frame_id(buffer)) % 255
        ramp = self._ramp(int(exposure_us), int(gain), int(pixel_format), w + h + 255)
        if ramp is None:  # a format this camera does not render: leave the buffer as it is
            return
        size = self._ct.c_size_t(0)
        addr = lib.arv_buffer_get_data(buffer, self._ct.byref(size))
        item = ramp.itemsize
        dest = np.ctypeslib.as_array((self._ct.c_uint8 * (w * h * item)).from_address(addr))
        dest = dest.view(ramp.dtype).reshape(h, w)
        src = np.lib.stride_tricks.as_strided(ramp[f:], shape=(h, w), strides=(item, item))
        np.copyto(dest, src)
        if edge is not None and w * h * item >= 8:
            dest.reshape(-1).view(np.uint8)[:8] = np.frombuffer(edge.to_bytes(8, "little"),
                                                                np.uint8)


def _serve(args: argparse.Namespace) -> int:
    """Body of the child process: create the fake camera and serve until told to stop."""
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    renderer = None
    if args.render:
        from galvo_driver.twin_render import Renderer

        try:
            renderer = Renderer.from_spec(json.loads(args.render))
        except (ValueError, OSError) as err:
            print(f"fake camera {args.serial}: render: {err}", file=sys.stderr, flush=True)
            return 1
        args.width, args.height = renderer.size
    gv = Aravis.GvFakeCamera.new_full("lo", args.serial, args.genicam)
    if gv is None or not gv.is_running():
        print(
            f"fake camera {args.serial}: could not serve on 'lo' (GVCP port 3956 taken?)",
            file=sys.stderr,
            flush=True,
        )
        return 1
    cam = gv.get_fake_camera()
    cam.set_trigger_frequency(args.trigger_frequency)
    for reg, value in (
        (_REG_SENSOR_WIDTH, args.width),
        (_REG_SENSOR_HEIGHT, args.height),
        (_REG_WIDTH, args.width),
        (_REG_HEIGHT, args.height),
        (_REG_EXPOSURE_US, 10000),
        (_REG_FRAME_PERIOD_US, 2000),
    ):
        cam.write_register(reg, value)
    name = (args.user_id or "").encode().ljust(_GVBS_USER_DEFINED_NAME_SIZE, b"\0")
    for i in range(0, _GVBS_USER_DEFINED_NAME_SIZE, 4):
        cam.write_register(_GVBS_USER_DEFINED_NAME + i, int.from_bytes(name[i : i + 4], "big"))

    cam.write_register(_REG_ARAVIS_TRIGGER_SOURCE, 1)
    cam.write_register(_REG_TRIGGER_SOURCE_SELECTED, 0)  # Line0, a camera's usual default

    fill = _RampFill() if renderer is None else _ImageFill()
    fill.install(cam)
    line = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    line.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    line.bind(("127.0.0.1", 0))

    def register(address: int) -> int:
        value = cam.read_register(address)  # PyGObject: (ok, value) for the out argument
        return value[-1] if isinstance(value, tuple) else value

    # Aravis 0.8's fake-camera thread computes its poll timeout from an unsigned time
    # difference: when it is even a microsecond late for its next slot (the trigger check
    # every 1 / trigger_frequency), the difference wraps and it sleeps 100 ms in g_poll --
    # with a trigger pending, every edge meanwhile is missed (about half of a 500 Hz
    # trigger stream). A datagram on its GVCP socket ends that poll (a register read; the
    # answer is drained): one is sent for each edge taken, and again every
    # _WAKE_PERIOD_S while that trigger is still pending.
    wake = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    wake.setblocking(False)

    def wake_streaming_thread() -> None:
        try:
            while wake.recv(64):
                pass
        except OSError:
            pass  # nothing left to drain
        try:
            wake.sendto(_GVCP_WAKE, ("127.0.0.1", _GVCP_PORT))
        except OSError:
            pass

    counts = collections.Counter()  # what became of the line's edges (stderr at exit)

    def trigger_line() -> None:  # the camera's trigger input Line0: one datagram per edge
        pending = False  # a trigger taken and not yet acknowledged by the streaming thread
        while True:
            line.settimeout(_WAKE_PERIOD_S if pending else None)
            try:
                data = line.recv(16)
            except TimeoutError:
                data = None
            except OSError:
                return
            if pending:
                pending = register(_REG_TRIGGER_SOFTWARE) != 0
                if pending:
                    wake_streaming_thread()
            if data is None:
                continue
            edge = int.from_bytes(data[:8], "little") if len(data) >= 8 else time.time_ns()
            counts["edges"] += 1
            if register(_REG_TRIGGER_MODE) != 1 or register(_REG_TRIGGER_SOURCE_SELECTED) != 0:
                counts["ignored (not the trigger source)"] += 1
                continue  # the line is not the trigger source: the edge does nothing
            if register(_REG_TRIGGER_SOFTWARE) != 0:  # still busy: this edge is missed
                counts["missed (previous trigger pending)"] += 1
            else:
                counts["taken"] += 1
                fill.edges.append(edge)
                cam.write_register(_REG_TRIGGER_SOFTWARE, 1)
                if args.wake_on_edge:
                    wake_streaming_thread()
                    pending = True

    stop = threading.Event()
    if renderer is None:
        threading.Thread(target=trigger_line, daemon=True).start()
    else:
        _render_threads(cam, fill, line, renderer, register, wake_streaming_thread, counts,
                        stop)
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())

    def watch_parent() -> None:  # the parent holds our stdin: EOF means it has gone
        inp = sys.stdin.buffer
        while True:
            cmd = inp.readline()
            if not cmd:
                break
            words = cmd.split()
            if renderer is not None and len(words) == 2 and words[0] == b"scene":
                text = inp.read(int(words[1])).decode("utf-8", "replace")
                try:
                    answer = f"ok {renderer.set_scene(text)}"
                except ValueError as err:
                    answer = "error " + " ".join(str(err).split())
                print(f"{_SCENE} {answer}", flush=True)
        stop.set()

    threading.Thread(target=watch_parent, daemon=True).start()
    print(_READY, line.getsockname()[1], flush=True)
    while not stop.wait(0.2):
        pass
    del gv  # stops the GVCP/GVSP thread and closes the sockets
    counts["frames made"] = fill.frames
    if renderer is not None:
        renderer.close()
    print(f"{_LINE_REPORT} {json.dumps(dict(counts), sort_keys=True)}", file=sys.stderr,
          flush=True)
    return 0


#: Line edges a rendering camera holds while it renders the ones before (beyond: missed).
_RENDER_QUEUE = 4096
#: How long a rendered frame waits for the streaming thread to take its trigger [s].
_TRIGGER_TAKE_TIMEOUT_S = 2.0


def _render_threads(cam, fill, line, renderer, register, wake, counts, stop) -> None:
    """Start a rendering camera's line and render threads.

    The line thread reads every edge datagram at once and queues it; the render thread
    renders the exposure at the edge's DAC outputs and laser level, then hands the image to
    the streaming thread as a software trigger, one at a time. So the simulator's render
    time delays frames but loses no edge (a camera that keeps up with its trigger); only
    more than ``_RENDER_QUEUE`` edges waiting are missed.
    """
    import queue

    from galvo_driver.serial_link.simavr_board import EDGE_FORMAT

    pending: queue.Queue = queue.Queue(_RENDER_QUEUE)

    def line_thread() -> None:
        while True:
            try:
                data = line.recv(64)
            except OSError:
                return
            counts["edges"] += 1
            if register(_REG_TRIGGER_MODE) != 1 or register(_REG_TRIGGER_SOURCE_SELECTED) != 0:
                counts["ignored (not the trigger source)"] += 1
            elif register(_REG_ACQUISITION) != 1:
                counts["ignored (not acquiring)"] += 1
            elif len(data) < EDGE_FORMAT.size:
                counts["ignored (no DAC outputs in the datagram)"] += 1
            else:
                try:
                    pending.put_nowait(EDGE_FORMAT.unpack_from(data))
                except queue.Full:
                    counts["missed (render queue full)"] += 1

    def render_thread() -> None:
        while not stop.is_set():
            try:
                edge, c0, c1, c2, c3, powered, range_code, laser, cycle = pending.get(
                    timeout=0.2)
            except queue.Empty:
                continue
            roi = (*(register(r) for r in (_REG_WIDTH, _REG_HEIGHT, _REG_OFFSET_X,
                                           _REG_OFFSET_Y)),
                   _PIXEL_DEPTH.get(register(_REG_PIXEL_FORMAT), 8))
            try:
                image = renderer.render(edge, (c0, c1, c2, c3), powered, range_code,
                                        bool(laser), register(_REG_EXPOSURE_US) * 1e-6, roi,
                                        cycle)
            except (ValueError, RuntimeError) as err:
                counts["not rendered"] += 1
                print(f"fake camera: edge {edge} not rendered: {err}", file=sys.stderr,
                      flush=True)
                continue
            deadline = time.monotonic() + _TRIGGER_TAKE_TIMEOUT_S
            while register(_REG_TRIGGER_SOFTWARE) != 0 and time.monotonic() < deadline:
                wake()  # the previous frame is still being made
                time.sleep(_WAKE_PERIOD_S)
            if register(_REG_TRIGGER_SOFTWARE) != 0:
                cam.write_register(_REG_TRIGGER_SOFTWARE, 0)  # not acquiring: withdrawn
                fill.images.clear()
                counts["missed (not acquiring)"] += 1
            fill.images.append((edge, image))
            counts["taken"] += 1
            cam.write_register(_REG_TRIGGER_SOFTWARE, 1)
            wake()

    threading.Thread(target=line_thread, daemon=True).start()
    threading.Thread(target=render_thread, daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    """Run one fake camera until SIGTERM/SIGINT or until stdin closes."""
    p = argparse.ArgumentParser(
        prog="python -m galvo_driver.fake_camera",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--serial", default="GSFAKE0")
    p.add_argument("--user-id", default="")
    p.add_argument("--width", type=int, default=720)
    p.add_argument("--height", type=int, default=540)
    p.add_argument("--trigger-frequency", type=float, default=4000.0, help="[Hz]")
    p.add_argument("--wake-on-edge", action="store_true",
                   help="wake the streaming thread on each line edge (see FakeCamera)")
    p.add_argument("--genicam", default=None, help="GenICam XML file (default: the built-in one)")
    p.add_argument("--render", default="",
                   help="JSON {rig, scene, seed, log}: render each line edge's exposure "
                        "(galvo_driver.twin_render) instead of the ramp")
    args = p.parse_args(argv)
    if args.genicam is None:
        tmp = tempfile.TemporaryDirectory(prefix="galvoscan-fakecam-")
        args.genicam = os.path.join(tmp.name, "galvoscan-fake-camera.xml")
        with open(args.genicam, "w", encoding="utf-8") as f:
            f.write(GENICAM_XML)
    return _serve(args)


if __name__ == "__main__":
    sys.exit(main())
