"""Load a replay fixture: per-device recordings of one scene plus its timing truth.

A fixture is a folder with ``fixture.toml``, one audio file per device and a ``truth/`` folder
(format in ``replay_fixtures/README.md``). Truth conventions (see ``estimators.conventions``):

- ``toa.csv``: ``time_s`` is a time on device 0's clock (its sample index / its nominal rate);
  ``toa_s_i`` is the time at which the direct-path wavefront that reaches device 0 at ``time_s``
  reaches device ``i``, read on device ``i``'s clock, minus ``time_s``. So ``toa_s_0 = 0`` and
  ``toa_s_i`` contains start offset, drift and propagation difference.
- ``sync_toa.csv``: the same for the synchronous signals ``sync.flac``; ``time_s`` is simulation
  time and ``toa_s_i`` is the pure propagation difference.
- Device-clock time of true time ``t``: ``T_i = (t - start_offset_s[i]) * (1 + drift_ppm[i] * 1e-6)``.
- Scenes with several sources (optional ``[sources]`` table): ``toa.csv`` follows the *active talker*
  (the last one who spoke), ``clean.flac`` is the sum of every talker's aligned dry signal, and each
  source has its own ``toa_<name>.csv``; ``activity.csv`` says who is active per 10 ms on device 0's clock.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import soundfile as sf

from ..errors import InputFileError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

__all__ = ["FixtureError", "FixtureDevice", "FixtureSource", "Fixture", "load_fixture", "is_fixture_dir"]

MANIFEST = "fixture.toml"
_DEVICE_KEYS = ("name", "file", "sample_rate_hz", "start_offset_s", "drift_ppm", "gain_db",
                "position_m")
_TRUTH_KEYS = ("clean", "toa", "sync", "clean_sync", "sync_toa", "source_path")


class FixtureError(InputFileError):
    """A fixture folder is missing, incomplete or malformed."""


@dataclass(frozen=True)
class FixtureDevice:
    """One recording device of a fixture.

    Attributes
    ----------
    name : str
    path : Path
        Audio file of the recording.
    sample_rate_hz : int
        Nominal rate of the file.
    start_offset_s : float
        True time at which the device started recording (simulation time).
    drift_ppm : float
        Actual rate is ``sample_rate_hz * (1 + drift_ppm * 1e-6)``.
    gain_db : float
        Gain applied to the device (sensitivity difference), before its sensor noise.
    position_m : ndarray, shape (3,), float64
    """

    name: str
    path: Path
    sample_rate_hz: int
    start_offset_s: float
    drift_ppm: float
    gain_db: float
    position_m: np.ndarray = field(repr=False, compare=False)

    def load(self) -> tuple[np.ndarray, int]:
        """Samples ``(n_samples,)`` float32 in [-1, 1) and the nominal rate in Hz."""
        x, rate = sf.read(str(self.path), dtype="float32", always_2d=True)
        return x[:, 0], int(rate)

    def clock_s(self, true_time_s):
        """Device-clock time of true time: ``T = (t - start_offset_s) * (1 + drift_ppm * 1e-6)``."""
        return (np.asarray(true_time_s) - self.start_offset_s) * (1.0 + self.drift_ppm * 1e-6)


@dataclass(frozen=True)
class FixtureSource:
    """One sound source of a multi-source scene: ``kind`` is ``"talker"`` or ``"noise:<what>"``."""

    name: str
    kind: str
    toa_path: Path
    position_m: np.ndarray = field(repr=False, compare=False)

    @property
    def is_noise(self) -> bool:
        return self.kind.startswith("noise")


@dataclass(frozen=True)
class Fixture:
    """A loaded ``fixture.toml``; audio and truth tables are read on demand."""

    root: Path
    name: str
    description: str
    working_rate_hz: int
    duration_s: float
    devices: tuple[FixtureDevice, ...]
    room: dict = field(repr=False, compare=False)
    truth_clean: Path | None = None
    truth_toa: Path | None = None
    truth_sync: Path | None = None
    truth_clean_sync: Path | None = None
    truth_sync_toa: Path | None = None
    truth_source_path: Path | None = None
    credits: dict = field(default_factory=dict, repr=False, compare=False)
    raw: dict = field(default_factory=dict, repr=False, compare=False)
    sources: tuple[FixtureSource, ...] = ()
    truth_activity: Path | None = None

    @property
    def n_devices(self) -> int:
        return len(self.devices)

    @property
    def positions_m(self) -> np.ndarray:
        """Device positions, shape (M, 3), metres."""
        return np.stack([d.position_m for d in self.devices])

    def load_truth_toa(self) -> tuple[np.ndarray, np.ndarray]:
        """``time_s`` (n,) on device 0's clock and ``toa_s`` (n, M), seconds."""
        return _read_toa_csv(self._need(self.truth_toa, "toa"), self.n_devices)

    def load_sync_toa(self) -> tuple[np.ndarray, np.ndarray]:
        """``time_s`` (n,) simulation time and ``toa_s`` (n, M) of the synchronous signals."""
        return _read_toa_csv(self._need(self.truth_sync_toa, "sync_toa"), self.n_devices)

    def load_clean(self) -> tuple[np.ndarray, int]:
        """Dry talker aligned to device 0's direct path: ``(n,)`` float32 and its rate in Hz."""
        x, rate = sf.read(str(self._need(self.truth_clean, "clean")), dtype="float32",
                          always_2d=True)
        return x[:, 0], int(rate)

    def load_sync(self) -> tuple[np.ndarray, int]:
        """Synchronous device signals ``(n, M)`` float32 and the working rate in Hz."""
        x, rate = sf.read(str(self._need(self.truth_sync, "sync")), dtype="float32",
                          always_2d=True)
        if x.shape[1] != self.n_devices:
            raise FixtureError(f"{self.truth_sync} has {x.shape[1]} channels, expected "
                               f"{self.n_devices} (one per device)")
        return x, int(rate)

    def load_clean_sync(self) -> tuple[np.ndarray, int]:
        """Dry talker aligned to sync channel 0's direct path: ``(n,)`` float32 and rate in Hz."""
        x, rate = sf.read(str(self._need(self.truth_clean_sync, "clean_sync")), dtype="float32",
                          always_2d=True)
        return x[:, 0], int(rate)

    def load_source_path(self) -> tuple[np.ndarray, np.ndarray]:
        """Talker emission time ``time_s`` (n,) (simulation time) and position (n, 3), metres."""
        path = self._need(self.truth_source_path, "source_path")
        a = _read_csv(path, ["time_s", "x_m", "y_m", "z_m"])
        return a[:, 0], a[:, 1:4]

    def truth_toa_at(self, time_s) -> np.ndarray:
        """Truth TOA at device-0 clock times, shape (len(time_s), M), seconds.

        Linear interpolation of ``toa.csv``; outside its grid the first/last segment is
        extended linearly (the TOA of a static talker is linear in time).
        """
        grid, toa = self.load_truth_toa()
        return _interp_columns(np.atleast_1d(np.asarray(time_s, float)), grid, toa)

    def source(self, name: str) -> FixtureSource:
        for src in self.sources:
            if src.name == name:
                return src
        raise FixtureError(f"fixture {self.name!r} has no source {name!r} (it has "
                           f"{[s.name for s in self.sources]})")

    def source_toa_at(self, name: str, time_s) -> np.ndarray:
        """TOA of source ``name`` at device-0 clock times, shape (len(time_s), M), seconds."""
        grid, toa = _read_toa_csv(self.source(name).toa_path, self.n_devices)
        return _interp_columns(np.atleast_1d(np.asarray(time_s, float)), grid, toa)

    def activity_at(self, time_s) -> tuple[np.ndarray, np.ndarray]:
        """Who is active at device-0 clock times: the active talker's index (int, held through
        pauses) and per-talker speaking flags (bool, shape (n, n_talkers)); nearest 10 ms row."""
        path = self._need(self.truth_activity, "activity")
        with open(path, encoding="utf-8") as f:
            header = f.readline().strip().split(",")
        a = _read_csv(path, header)
        t = np.atleast_1d(np.asarray(time_s, float))
        i = np.clip(np.searchsorted(a[:, 0], t - 0.005), 0, len(a) - 1)
        return a[i, 1].astype(int), a[i, 2:].astype(bool)

    def _need(self, path: Path | None, key: str) -> Path:
        if path is None:
            raise FixtureError(f"fixture {self.name!r} has no truth {key!r} in {self.root / MANIFEST}")
        return path


def _interp_columns(t: np.ndarray, grid: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.stack([np.interp(t, grid, values[:, m]) for m in range(values.shape[1])], axis=1)
    if len(grid) >= 2:
        lo, hi = t < grid[0], t > grid[-1]
        if lo.any():
            slope = (values[1] - values[0]) / (grid[1] - grid[0])
            out[lo] = values[0] + (t[lo, None] - grid[0]) * slope
        if hi.any():
            slope = (values[-1] - values[-2]) / (grid[-1] - grid[-2])
            out[hi] = values[-1] + (t[hi, None] - grid[-1]) * slope
    return out


def _read_csv(path: Path, expected_header: list[str]) -> np.ndarray:
    with open(path, encoding="utf-8") as f:
        header = f.readline().strip().split(",")
    if header != expected_header:
        raise FixtureError(f"{path} header is {header}, expected {expected_header}")
    try:
        return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as e:
        raise FixtureError(f"{path} is not a numeric CSV table: {e}") from e


def _read_toa_csv(path: Path, n_devices: int) -> tuple[np.ndarray, np.ndarray]:
    a = _read_csv(path, ["time_s"] + [f"toa_s_{i}" for i in range(n_devices)])
    return a[:, 0], a[:, 1:]


def is_fixture_dir(path) -> bool:
    """True if ``path`` is a folder holding a ``fixture.toml``."""
    p = Path(path)
    return p.is_dir() and (p / MANIFEST).is_file()


def _get(table: dict, key: str, where: str, kind=None):
    if key not in table:
        raise FixtureError(f"{where} is missing the key {key!r}")
    v = table[key]
    if kind is not None and not isinstance(v, kind):
        raise FixtureError(f"{where} key {key!r} = {v!r} has the wrong type "
                           f"(expected {getattr(kind, '__name__', kind)})")
    return v


def load_fixture(path) -> Fixture:
    """Read ``path/fixture.toml`` (or the toml file itself) and check that the files exist.

    Raises
    ------
    FixtureError
        Missing ``fixture.toml``, malformed TOML, a missing key, or a missing device/truth file.
    """
    p = Path(path)
    manifest = p if p.is_file() else p / MANIFEST
    root = manifest.parent
    if not manifest.is_file():
        raise FixtureError(f"no {MANIFEST} in {root}: not a replay fixture folder")
    try:
        doc = tomllib.loads(manifest.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise FixtureError(f"{manifest} is not valid TOML: {e}") from e
    where = str(manifest)
    number = (int, float)
    name = _get(doc, "name", where, str)
    rows = _get(doc, "device", where, list)
    if not rows:
        raise FixtureError(f"{where} has no [[device]] tables")
    devices = []
    for i, row in enumerate(rows):
        w = f"{where} [[device]] #{i}"
        if not isinstance(row, dict):
            raise FixtureError(f"{w} is not a table")
        for k in _DEVICE_KEYS:
            _get(row, k, w)
        pos = np.asarray(_get(row, "position_m", w, list), dtype=float)
        if pos.shape != (3,):
            raise FixtureError(f"{w} position_m must be [x, y, z] in metres, got {row['position_m']!r}")
        file = root / _get(row, "file", w, str)
        if not file.is_file():
            raise FixtureError(f"device file {file} listed in {where} does not exist")
        rate = _get(row, "sample_rate_hz", w, int)
        if rate <= 0:
            raise FixtureError(f"{w} sample_rate_hz={rate} must be > 0")
        devices.append(FixtureDevice(
            name=_get(row, "name", w, str), path=file, sample_rate_hz=rate,
            start_offset_s=float(_get(row, "start_offset_s", w, number)),
            drift_ppm=float(_get(row, "drift_ppm", w, number)),
            gain_db=float(_get(row, "gain_db", w, number)), position_m=pos))
    truth = doc.get("truth", {})
    if not isinstance(truth, dict):
        raise FixtureError(f"{where} [truth] is not a table")
    truth_paths = {}
    for k in _TRUTH_KEYS:
        if k in truth:
            f = root / _get(truth, k, f"{where} [truth]", str)
            if not f.is_file():
                raise FixtureError(f"truth file {f} listed in {where} does not exist")
            truth_paths[k] = f
        else:
            truth_paths[k] = None
    room = _get(doc, "room", where, dict)
    _get(room, "dims_m", f"{where} [room]", list)
    sources, activity = (), None
    if "sources" in doc:
        w = f"{where} [sources]"
        tab = _get(doc, "sources", where, dict)
        names, kinds = _get(tab, "names", w, list), _get(tab, "kinds", w, list)
        files, pos = _get(tab, "toa", w, list), _get(tab, "positions_m", w, list)
        if not len(names) == len(kinds) == len(files) == len(pos):
            raise FixtureError(f"{w} names, kinds, toa and positions_m must have the same length")
        for f in files + [_get(tab, "activity", w, str)]:
            if not (root / f).is_file():
                raise FixtureError(f"truth file {root / f} listed in {w} does not exist")
        sources = tuple(FixtureSource(str(n), str(k), root / f, np.asarray(p, float))
                        for n, k, f, p in zip(names, kinds, files, pos))
        activity = root / tab["activity"]
    return Fixture(
        root=root, name=name, description=str(doc.get("description", "")),
        working_rate_hz=int(_get(doc, "working_rate_hz", where, int)),
        duration_s=float(_get(doc, "duration_s", where, number)),
        devices=tuple(devices), room=dict(room),
        truth_clean=truth_paths["clean"], truth_toa=truth_paths["toa"],
        truth_sync=truth_paths["sync"], truth_clean_sync=truth_paths["clean_sync"],
        truth_sync_toa=truth_paths["sync_toa"], truth_source_path=truth_paths["source_path"],
        credits=dict(doc.get("credits", {})), raw=doc, sources=sources, truth_activity=activity)
