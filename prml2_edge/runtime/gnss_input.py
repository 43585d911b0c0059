"""GNSS fixes from where they really come from: a receiver's NMEA, gpsd, or a file of fixes.

``prml2 replay --gnss FILE`` merges recorded fixes with the CAN log by time; ``prml2 run --gnss
SOURCE`` reads them live. Every source yields :class:`~prml2_edge.runtime.rows.GnssFix` in the
runtime's local frame (x east, y north [m], heading clockwise from north [deg]):

* **NMEA log** (``.nmea``, or any text file whose lines start with ``$``): GGA (position, fix
  quality) and RMC (date, course over ground, status) with valid checksums, parsed by pynmea2;
  sentences of one epoch make one fix; its time is RMC's UTC date and time as a Unix time, so it
  lines up with a CAN log stamped in Unix time (candump, python-can's loggers). A log on another
  clock takes ``--gnss-time-offset S``.
* **CSV of fixes** (``.csv``): columns ``t_s, x_m, y_m`` and optionally ``heading_deg``, already
  in local metres on the CAN log's clock.
* **TUM trajectory** (``.tum``): ``timestamp x y z qx qy qz qw`` in local metres; the quaternion's
  yaw (counter-clockwise from east, ``evo``'s convention) carries the course.
* **gpsd** (``gpsd://HOST:PORT``, default port 2947): gpsd's JSON protocol (``?WATCH``, TPV reports).
* **serial NMEA** (``/dev/ttyUSB0`` or ``serial:///dev/ttyACM0?baud=9600``): a receiver on a serial port.

Latitude/longitude become local metres on a tangent plane (east, north; WGS-84, pymap3d's
``geodetic2enu``, the plane's height that of the origin): the origin is ``--gnss-origin LAT,LON``
when given (what a map of the site or a previous run used), else the first valid fix, so a run
starts near (0, 0) as the project's frames do (method.md: ``ins_pos_rel_x/y`` are metres east and
north of a local origin). Live fixes are stamped with this box's clock on receipt, the clock
socketcan stamps frames with.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import math
import queue
import socket
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from urllib.parse import parse_qs, urlparse

from prml2_edge.errors import ConfigError, DataError, first_line
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.schema import psi_rad_to_heading_deg

KNOT_MPS = 0.514444


class LocalFrame:
    """WGS-84 latitude/longitude to local east/north metres on a tangent plane at an origin.

    ``origin`` (lat, lon) in degrees, or None: the first point converted becomes the origin.
    """

    def __init__(self, origin: tuple[float, float] | None = None) -> None:
        self.origin = origin

    @staticmethod
    def parse(text: str | None) -> LocalFrame:
        """``"LAT,LON"`` (degrees) or None/empty (origin at the first fix)."""
        if not text:
            return LocalFrame()
        try:
            lat, lon = (float(v) for v in text.split(","))
        except ValueError:
            raise ConfigError(f"--gnss-origin must be LAT,LON in degrees (e.g. 48.1351,11.5820), got {text!r}") \
                from None
        if not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise ConfigError(f"--gnss-origin {text!r}: latitude must be within +-90, longitude within +-180 degrees")
        return LocalFrame((lat, lon))

    def to_local(self, lat: float, lon: float) -> tuple[float, float]:
        import pymap3d

        if self.origin is None:
            self.origin = (lat, lon)
        east, north, _ = pymap3d.geodetic2enu(lat, lon, 0.0, self.origin[0], self.origin[1], 0.0)
        return float(east), float(north)

    def to_geodetic(self, x_m: float, y_m: float) -> tuple[float, float]:
        """Inverse of :meth:`to_local` (needs an origin)."""
        import pymap3d

        assert self.origin is not None
        lat, lon, _ = pymap3d.enu2geodetic(x_m, y_m, 0.0, self.origin[0], self.origin[1], 0.0)
        return float(lat), float(lon)


# ---- NMEA ---------------------------------------------------------------------------------------

class NmeaAssembler:
    """NMEA sentences -> fixes: GGA and RMC of one UTC epoch make one fix (emitted when the epoch changes).

    ``clock`` None: the fix time is RMC's UTC date and time (Unix seconds); a callable: the fix is
    stamped with ``clock()`` when its epoch completes (live receivers).
    """

    def __init__(self, frame: LocalFrame, clock=None, time_offset_s: float = 0.0) -> None:
        self.frame = frame
        self.clock = clock
        self.time_offset_s = time_offset_s
        self.date: dt.date | None = None
        self._epoch: dt.time | None = None
        self._cur: dict = {}
        self.bad_sentences = 0
        self.sentences = 0

    def feed(self, line: str) -> list[GnssFix]:
        """One line; returns the fixes it completed (0 or 1). A bad sentence is counted, never raised."""
        import pynmea2

        line = line.strip()
        if not line.startswith("$"):
            return []
        try:
            msg = pynmea2.parse(line, check=True)
        except (pynmea2.ParseError, ValueError, AttributeError):
            self.bad_sentences += 1
            return []
        self.sentences += 1
        kind = getattr(msg, "sentence_type", "")
        if kind not in ("GGA", "RMC"):
            return []
        stamp = getattr(msg, "timestamp", None)
        if stamp is None:
            return []
        out = []
        if self._epoch is not None and stamp != self._epoch:
            fix = self._emit()
            if fix is not None:
                out.append(fix)
        self._epoch = stamp
        if kind == "RMC":
            if getattr(msg, "datestamp", None) is not None:
                self.date = msg.datestamp
            self._cur["rmc_valid"] = msg.status == "A"
            if msg.true_course not in (None, ""):
                self._cur["course"] = float(msg.true_course)
            if msg.spd_over_grnd not in (None, ""):
                self._cur["speed"] = float(msg.spd_over_grnd) * KNOT_MPS
            if msg.latitude or msg.longitude:
                self._cur.setdefault("latlon", (msg.latitude, msg.longitude))
        else:
            self._cur["gga_valid"] = int(msg.gps_qual or 0) > 0
            if msg.lat:
                self._cur["latlon"] = (msg.latitude, msg.longitude)  # GGA's position wins
        return out

    def flush(self) -> list[GnssFix]:
        fix = self._emit() if self._epoch is not None else None
        self._epoch = None
        return [fix] if fix is not None else []

    def _emit(self) -> GnssFix | None:
        cur, self._cur = self._cur, {}
        if "latlon" not in cur:
            return None
        valid = cur.get("gga_valid", True) and cur.get("rmc_valid", True)
        if self.clock is not None:
            t_s = float(self.clock())
        else:
            if self.date is None:
                return None  # placed once an RMC gives the date
            t_s = dt.datetime.combine(self.date, self._epoch.replace(tzinfo=None)).replace(  # type: ignore[union-attr]
                tzinfo=dt.UTC).timestamp()
        x, y = self.frame.to_local(*cur["latlon"]) if valid else (math.nan, math.nan)
        return GnssFix(t_s + self.time_offset_s, x, y, cur.get("course"), bool(valid and math.isfinite(x)))


def read_nmea(path: Path, frame: LocalFrame, time_offset_s: float = 0.0) -> list[GnssFix]:
    nmea = NmeaAssembler(frame, time_offset_s=time_offset_s)
    fixes: list[GnssFix] = []
    with open(path, encoding="ascii", errors="replace") as f:
        for line in f:
            fixes += nmea.feed(line)
    fixes += nmea.flush()
    if nmea.sentences and nmea.date is None:
        raise DataError(f"{path}: no RMC sentence with a date: GGA times alone cannot be placed on the CAN log's "
                        "clock; record RMC too (gpspipe -r writes both)")
    if not fixes:
        bad = f" ({nmea.bad_sentences} sentences with bad checksums or fields)" if nmea.bad_sentences else ""
        raise DataError(f"{path}: no GGA/RMC fix in this NMEA log{bad}")
    return fixes


# ---- CSV / TUM ----------------------------------------------------------------------------------

def read_fix_csv(path: Path, time_offset_s: float = 0.0) -> list[GnssFix]:
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.DictReader(f)
        cols = [c.strip() for c in (reader.fieldnames or [])]
        missing = [c for c in ("t_s", "x_m", "y_m") if c not in cols]
        if missing:
            raise DataError(f"{path}: GNSS CSV lacks column(s) {', '.join(missing)}; expected t_s, x_m, y_m "
                            "[, heading_deg] (seconds on the CAN log's clock, metres east/north, degrees clockwise "
                            "from north)")
        fixes = []
        for row_no, row in enumerate(reader, start=1):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k}
            try:
                t, x, y = float(row["t_s"]), float(row["x_m"]), float(row["y_m"])
                h = float(row["heading_deg"]) if row.get("heading_deg") else None
            except ValueError:
                raise DataError(f"{path}: row {row_no}: not a number in {row}") from None
            fixes.append(GnssFix(t + time_offset_s, x, y, h, math.isfinite(x) and math.isfinite(y)))
    if not fixes:
        raise DataError(f"{path}: GNSS CSV holds no fixes")
    return fixes


def read_tum(path: Path, time_offset_s: float = 0.0) -> list[GnssFix]:
    fixes = []
    with open(path, encoding="utf-8") as f:
        for line_no, line in enumerate(f, start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            if len(parts) != 8:
                raise DataError(f"{path}: line {line_no}: a TUM line has 8 fields (timestamp x y z qx qy qz qw), "
                                f"this one {len(parts)}")
            try:
                t, x, y, _z, qx, qy, qz, qw = (float(p) for p in parts)
            except ValueError:
                raise DataError(f"{path}: line {line_no}: not a number") from None
            psi = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
            fixes.append(GnssFix(t + time_offset_s, x, y, float(psi_rad_to_heading_deg(psi)), True))
    if not fixes:
        raise DataError(f"{path}: TUM file holds no poses")
    return fixes


def load_fixes(path: str | Path, frame: LocalFrame | None = None, time_offset_s: float = 0.0) -> list[GnssFix]:
    """Fixes from a file, sorted by time: NMEA (``.nmea``, or lines starting with ``$``), CSV (``.csv``) or TUM."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: GNSS file not found")
    frame = frame or LocalFrame()
    suffix = path.suffix.lower()
    if suffix == ".csv":
        fixes = read_fix_csv(path, time_offset_s)
    elif suffix == ".tum":
        fixes = read_tum(path, time_offset_s)
    else:
        with open(path, encoding="ascii", errors="replace") as f:
            first = next((ln.strip() for ln in f if ln.strip() and not ln.startswith("#")), "")
        if first.startswith("$") or suffix == ".nmea":
            fixes = read_nmea(path, frame, time_offset_s)
        elif len(first.split()) == 8:
            fixes = read_tum(path, time_offset_s)
        else:
            raise DataError(f"{path}: not an NMEA log, a CSV (t_s,x_m,y_m[,heading_deg]) or a TUM file of fixes")
    fixes.sort(key=lambda f: f.t_s)
    return fixes


class FixFeed:
    """Recorded fixes handed to the pipeline in time order: :meth:`due` returns those up to frame time ``t_s``."""

    def __init__(self, fixes: list[GnssFix], describe: str = "") -> None:
        self.fixes = sorted(fixes, key=lambda f: f.t_s)
        self.describe = describe
        self._i = 0

    def due(self, t_s: float) -> list[GnssFix]:
        j = self._i
        while j < len(self.fixes) and self.fixes[j].t_s <= t_s:
            j += 1
        out, self._i = self.fixes[self._i:j], j
        return out

    def summary(self) -> dict:
        return {"source": self.describe, "fixes": len(self.fixes), "merged": self._i}


def check_overlap(fixes: list[GnssFix], t_first: float, t_last: float, where: str) -> None:
    """Refuse fixes that do not overlap the CAN log in time (a clock or offset mistake), in one line."""
    a, b = fixes[0].t_s, fixes[-1].t_s
    if b < t_first or a > t_last:
        raise DataError(f"{where}: the fixes cover {a:.3f}..{b:.3f} s, the CAN log {t_first:.3f}..{t_last:.3f} s: "
                        f"they do not overlap; shift them with --gnss-time-offset {t_first - a:+.3f} ([gnss] "
                        "time_offset_s in the config) if the clocks differ")


# ---- live sources -------------------------------------------------------------------------------

class LiveGnss:
    """A receiver read in a background thread; :meth:`pop` returns the fixes that arrived since the last call."""

    def __init__(self, describe: str) -> None:
        self.describe = describe
        self.fixes = 0
        self.errors = 0
        self.last_error = ""
        self._q: queue.Queue[GnssFix] = queue.Queue(maxsize=1000)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> LiveGnss:
        self._thread = threading.Thread(target=self._loop, name="prml2-gnss", daemon=True)
        self._thread.start()
        return self

    def _put(self, fix: GnssFix) -> None:
        self.fixes += 1
        try:
            self._q.put_nowait(fix)
        except queue.Full:  # nobody is reading: drop the oldest
            self._q.get_nowait()
            self._q.put_nowait(fix)

    def due(self, t_s: float) -> list[GnssFix]:
        """Every fix that arrived (live fixes are stamped on receipt: all are due)."""
        return self.pop()

    def pop(self) -> list[GnssFix]:
        out = []
        while True:
            try:
                out.append(self._q.get_nowait())
            except queue.Empty:
                return out

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._run()
            except Exception as exc:  # a receiver that drops out: count it, retry after a second
                self.errors += 1
                self.last_error = first_line(exc, 200)
            self._stop.wait(1.0)

    def _run(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def summary(self) -> dict:
        return {"source": self.describe, "fixes": self.fixes, "errors": self.errors, "last_error": self.last_error}


class GpsdSource(LiveGnss):
    """gpsd over TCP: ``?WATCH={"enable":true,"json":true}``, then TPV reports (mode 2/3 = 2D/3D fix)."""

    def __init__(self, host: str, port: int, frame: LocalFrame, clock=time.time) -> None:
        super().__init__(f"gpsd://{host}:{port}")
        self.host, self.port, self.frame, self.clock = host, port, frame, clock
        self.version: dict | None = None

    def _run(self) -> None:
        with socket.create_connection((self.host, self.port), timeout=5.0) as sock:
            sock.settimeout(0.5)
            sock.sendall(b'?WATCH={"enable":true,"json":true};\n')
            buf = b""
            while not self._stop.is_set():
                try:
                    chunk = sock.recv(4096)
                except TimeoutError:
                    continue
                if not chunk:
                    raise ConnectionError("gpsd closed the connection")
                buf += chunk
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    self._report(line)

    def _report(self, line: bytes) -> None:
        try:
            rep = json.loads(line)
        except ValueError:
            self.errors += 1
            return
        cls = rep.get("class")
        if cls == "VERSION":
            self.version = rep
        elif cls == "TPV":
            mode = int(rep.get("mode", 0) or 0)
            lat, lon = rep.get("lat"), rep.get("lon")
            if mode < 2 or lat is None or lon is None:
                self._put(GnssFix(float(self.clock()), math.nan, math.nan, None, False))
                return
            x, y = self.frame.to_local(float(lat), float(lon))
            track = rep.get("track")
            self._put(GnssFix(float(self.clock()), x, y, float(track) if track is not None else None, True))


class SerialNmeaSource(LiveGnss):
    """NMEA from a serial receiver (pyserial)."""

    def __init__(self, device: str, baud: int, frame: LocalFrame, clock=time.time) -> None:
        super().__init__(f"serial://{device}?baud={baud}")
        self.device, self.baud = device, baud
        self.nmea = NmeaAssembler(frame, clock=clock)

    def _run(self) -> None:
        import serial

        with serial.Serial(self.device, self.baud, timeout=0.5) as port:
            while not self._stop.is_set():
                raw = port.readline()
                if not raw:
                    continue
                for fix in self.nmea.feed(raw.decode("ascii", errors="replace")):
                    self._put(fix)


def open_live(spec: str, frame: LocalFrame, where: str = "--gnss") -> LiveGnss:
    """``gpsd://HOST[:PORT]``, ``serial:///dev/X[?baud=N]`` or a device path; one-line error otherwise, naming
    ``where`` the spec came from (the flag or the config key)."""
    if spec.startswith("gpsd://"):
        u = urlparse(spec)
        if not u.hostname:
            raise ConfigError(f"{where} {spec!r}: give gpsd://HOST[:PORT] (gpsd listens on port 2947)")
        return GpsdSource(u.hostname, u.port or 2947, frame)
    if spec.startswith("serial://") or spec.startswith("/dev/"):
        u = urlparse(spec) if spec.startswith("serial://") else None
        device = u.path if u is not None else spec
        baud = int(parse_qs(u.query).get("baud", ["9600"])[0]) if u is not None else 9600
        if not Path(device).exists():
            raise ConfigError(f"{where} {spec!r}: serial device {device} not found (is the receiver plugged in?)")
        return SerialNmeaSource(device, baud, frame)
    raise ConfigError(f"{where} {spec!r}: for a live run give gpsd://HOST[:PORT] or a serial device "
                      "(/dev/ttyACM0, serial:///dev/ttyUSB0?baud=38400)")


# ---- writing (tests, tools) ---------------------------------------------------------------------

def nmea_sentence(body: str) -> str:
    """``$BODY*CS`` with the XOR checksum of ``body``."""
    cs = 0
    for ch in body:
        cs ^= ord(ch)
    return f"${body}*{cs:02X}"


def _nmea_angle(value: float, lat: bool) -> tuple[str, str]:
    hemi = ("N" if value >= 0 else "S") if lat else ("E" if value >= 0 else "W")
    a = abs(value)
    deg = int(a)
    minutes = (a - deg) * 60.0
    width = 2 if lat else 3
    return f"{deg:0{width}d}{minutes:010.7f}", hemi


def fix_sentences(t_s: float, lat: float, lon: float, course_deg: float | None, speed_mps: float = 0.0,
                  talker: str = "GN") -> Iterable[str]:
    """GGA and RMC sentences (with checksums) of one fix at Unix time ``t_s``."""
    when = dt.datetime.fromtimestamp(round(t_s, 2), tz=dt.UTC)
    hms = when.strftime("%H%M%S") + f".{when.microsecond // 10000:02d}"
    la, ns = _nmea_angle(lat, True)
    lo, ew = _nmea_angle(lon, False)
    yield nmea_sentence(f"{talker}GGA,{hms},{la},{ns},{lo},{ew},1,12,0.8,520.0,M,47.0,M,,")
    course = f"{course_deg % 360.0:.3f}" if course_deg is not None else ""
    yield nmea_sentence(f"{talker}RMC,{hms},A,{la},{ns},{lo},{ew},{speed_mps / KNOT_MPS:.3f},{course},"
                        f"{when.strftime('%d%m%y')},,,A")
