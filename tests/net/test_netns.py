"""Router, devices and aggregator in three network namespaces, with ~5 % of the devices' packets dropped.

Topology (one bridge in its own namespace; the root namespace has no address on this network)::

    NS_r  10.P.Q.1  router           (stream.cli router)
    NS_d  10.P.Q.2  phone0..phone2   (stream.cli device, meeting_table dev00..dev02 replayed at real time)
    NS_a  10.P.Q.3  aggregator       (stream.cli aggregate --until-done)

nftables in NS_d drops 5 % of every packet the devices send to the router (``numgen random``; netem is not
available on this kernel, ``../shared/ENV.md`` section 3). Zenoh runs over TCP, so the drops become retransmits:
every frame must still arrive (or be counted lost and concealed), and the counter on the drop rule proves that
packets really were dropped. Needs root, ``ip`` and ``nft``; skips otherwise. Takes about 13 s.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import soundfile as sf

from tests.conftest import REPO_FIXTURES

FX = REPO_FIXTURES / "meeting_table"
REPO = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-m", "stream.cli"]
N_DEVICES = 3
ARRAY = "netns"
LOSS_PERCENT = 5
DEADLINE_S = 50.0              # the whole test, setup to teardown, stays below this
FRAME_SAMPLES = 1024           # the device agent's default frame (one lost frame conceals at least this)


def _run(*args: str, check: bool = True, timeout: float = 10.0) -> subprocess.CompletedProcess:
    p = subprocess.run(list(args), capture_output=True, text=True, timeout=timeout)
    if check and p.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({p.returncode}): {p.stderr.strip()}")
    return p


class Netns:
    """Namespaces named after the pid, a bridge, veth pairs, and the processes started in them."""

    def __init__(self, tmp: Path) -> None:
        pid = os.getpid()
        self.tag = f"aa{pid}"
        self.subnet = f"10.{(pid >> 8) & 255}.{pid & 255}"
        self.tmp = tmp
        self.names: list[str] = []
        self.procs: list[subprocess.Popen] = []
        self.logs: dict[str, Path] = {}

    def ns(self, role: str) -> str:
        return f"{self.tag}{role}"

    def add_ns(self, role: str) -> str:
        name = self.ns(role)
        _run("ip", "netns", "add", name)
        self.names.append(name)
        _run("ip", "-n", name, "link", "set", "lo", "up")
        return name

    def build(self) -> None:
        sw = self.ns("s")                         # created first, by the fixture (it skips if that fails)
        _run("ip", "-n", sw, "link", "add", "br0", "type", "bridge")
        _run("ip", "-n", sw, "link", "set", "br0", "up")
        for i, role in enumerate("rda", start=1):
            ns = self.add_ns(role)
            # both ends created inside namespaces: nothing appears in the root namespace
            _run("ip", "link", "add", "name", "e0", "netns", ns, "type", "veth", "peer", "name", f"p{role}",
                 "netns", sw)
            _run("ip", "-n", sw, "link", "set", f"p{role}", "master", "br0", "up")
            _run("ip", "-n", ns, "addr", "add", f"{self.subnet}.{i}/24", "dev", "e0")
            _run("ip", "-n", ns, "link", "set", "e0", "up")

    def addr(self, role: str) -> str:
        return f"{self.subnet}.{' rda'.index(role)}"

    def spawn(self, role: str, label: str, *args: str) -> subprocess.Popen:
        log = self.tmp / f"{label}.log"
        self.logs[label] = log
        with open(log, "w") as fh:
            p = subprocess.Popen(["ip", "netns", "exec", self.ns(role), *map(str, args)], stdout=fh,
                                 stderr=subprocess.STDOUT, cwd=REPO, start_new_session=True,
                                 env=dict(os.environ, PYTHONUNBUFFERED="1"))
        self.procs.append(p)
        return p

    def log(self, label: str) -> str:
        p = self.logs.get(label)
        return p.read_text(errors="replace") if p and p.exists() else ""

    def all_logs(self) -> str:
        return "\n".join(f"--- {k} ---\n{self.log(k)[-3000:]}" for k in self.logs)

    def teardown(self) -> None:
        for p in self.procs:                      # ip netns exec execs: p.pid is the python process
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        t_end = time.monotonic() + 3.0
        for p in self.procs:
            try:
                p.wait(max(0.1, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        for name in reversed(self.names):
            # anything still inside one of our namespaces was started by this test
            pids = _run("ip", "netns", "pids", name, check=False).stdout.split()
            for pid in pids:
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            _run("ip", "netns", "del", name, check=False)
        self.names = []


@pytest.fixture
def netns(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("network-namespace test needs root (ip netns, nft)")
    for tool in ("ip", "nft"):
        if shutil.which(tool) is None:
            pytest.skip(f"network-namespace test needs the '{tool}' command (apt-get install iproute2 nftables)")
    pytest.importorskip("zenoh")
    net = Netns(tmp_path)
    try:
        try:
            net.add_ns("s")
        except RuntimeError as err:
            pytest.skip(f"cannot create network namespaces here ({err})")
        net.build()
        yield net
    finally:
        net.teardown()


def _wait_for(cond, timeout_s: float, what: str, net: Netns, every_s: float = 0.05):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        v = cond()
        if v:
            return v
        time.sleep(every_s)
    raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}\n{net.all_logs()}")


PROBE = """
import sys, time, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"client"')
c.insert_json5("connect/endpoints", '["%s"]')
c.insert_json5("scouting/multicast/enabled", "false")
c.insert_json5("transport/shared_memory/enabled", "false")
s = zenoh.open(c)
t_end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < t_end:
    if any(r.ok is not None for r in s.liveliness().get("%s", timeout=0.5)):
        print("ready", flush=True)
        break
    time.sleep(0.05)
s.close()
"""


def test_devices_reach_the_aggregator_through_a_lossy_network(netns, tmp_path):
    t0 = time.monotonic()
    net = netns
    endpoint = f"tcp/{net.addr('r')}:7447"
    znet = ["--mode", "client", "--connect", endpoint, "--no-scouting", "--array", ARRAY]

    # 5 % of what the devices' namespace sends to the router is dropped
    nsd = net.ns("d")
    table = "adhocloss"
    _run("ip", "netns", "exec", nsd, "nft", "add", "table", "inet", table)
    _run("ip", "netns", "exec", nsd, "nft", "add", "chain", "inet", table, "out",
         "{ type filter hook output priority 0; policy accept; }")
    _run("ip", "netns", "exec", nsd, "nft", "add", "rule", "inet", table, "out", "ip", "daddr", net.addr("r"),
         "numgen", "random", "mod", "100", "lt", str(LOSS_PERCENT), "counter", "drop")

    router = net.spawn("r", "router", *CLI, "router", "--listen", endpoint, "--no-scouting")
    _wait_for(lambda: "listening on" in net.log("router") or router.poll() is not None, 15, "the router", net)
    assert router.poll() is None, f"the router exited\n{net.all_logs()}"

    out = tmp_path / "out"
    names = [f"phone{k}" for k in range(N_DEVICES)]
    agg = net.spawn("a", "aggregate", *CLI, "aggregate", "--out", out, *znet, "--expect", ",".join(names),
                    "--until-done", "--no-plots", "--no-progress", "--discover-s", "15")
    # the devices start once the aggregator listens (its liveliness token is declared after its subscribers):
    # frames sent before that would never reach it (plain pub/sub has no history)
    key = f"adhoc/{ARRAY}/aggregator/alive"
    probe = net.spawn("a", "probe", sys.executable, "-c", PROBE % (endpoint, key), "20")
    _wait_for(lambda: probe.poll() is not None, 22, "the aggregator's liveliness token", net)
    assert "ready" in net.log("probe"), f"the aggregator never became ready\n{net.all_logs()}"

    devices = [net.spawn("d", name, *CLI, "device", "--name", name, "--input", FX / f"dev{k:02d}.flac", *znet)
               for k, name in enumerate(names)]
    try:
        rc = agg.wait(timeout=max(5.0, DEADLINE_S - (time.monotonic() - t0)))
    except subprocess.TimeoutExpired:
        pytest.fail(f"the aggregator did not end within {DEADLINE_S:g} s of the test's start\n{net.all_logs()}")
    for d in devices:                             # they end before the aggregator does (--until-done)
        try:
            d.wait(timeout=max(1.0, DEADLINE_S + 5 - (time.monotonic() - t0)))
        except subprocess.TimeoutExpired:
            pytest.fail(f"a device agent did not end\n{net.all_logs()}")
    logs = net.all_logs()
    assert rc == 0, f"aggregate exited {rc}\n{logs}"

    # the drop rule really dropped packets (else this test proves nothing about loss)
    ruleset = json.loads(_run("ip", "netns", "exec", nsd, "nft", "-j", "list", "table", "inet", table).stdout)
    counters = [e["counter"] for item in ruleset["nftables"] if "rule" in item
                for e in item["rule"]["expr"] if "counter" in e]
    assert len(counters) == 1
    n_dropped = counters[0]["packets"]
    assert n_dropped > 0, f"nft dropped nothing: the loss was not applied\n{logs}"

    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "ok", report.get("messages")
    per_net = report["network"]["devices"]
    per_dev = {d["name"]: d for d in report["devices"]}
    figures = []
    for k, name in enumerate(names):
        m = re.search(rf"device {name}: sent (\d+) frames \((\d+) samples", net.log(name))
        assert m, f"device {name} did not finish cleanly\n{logs}"
        sent_frames, sent_samples = int(m[1]), int(m[2])
        assert devices[k].returncode == 0, f"device {name} exited {devices[k].returncode}\n{logs}"
        assert sent_samples == sf.info(str(FX / f"dev{k:02d}.flac")).frames
        c, d = per_net[name], per_dev[name]
        assert c["n_malformed"] == 0 and c["n_restarts"] == 0 and c["n_overrun_frames"] == 0, c
        assert c["n_departures"] == 0, c          # a device that ended cleanly did not "leave"
        # TCP retransmits: every frame arrives; a frame that did not is counted lost and its audio concealed
        assert c["n_frames"] - c["n_duplicates"] + c["n_lost_frames"] == sent_frames, c
        if c["n_lost_frames"] or c["n_late_frames"]:
            assert c["n_concealed_samples"] >= FRAME_SAMPLES, c
        # every sent sample reached the engine, or its place was concealed and counted
        real = d["n_samples"] - d["n_gap_samples"]
        assert real + c["n_concealed_samples"] >= sent_samples, (name, d, c)
        assert d["n_samples"] >= sent_samples, (name, d, c)      # real or concealed, the whole recording
        figures.append(f"{name}: {c['n_frames']}/{sent_frames} frames, lost {c['n_lost_frames']}, late "
                       f"{c['n_late_frames']}, concealed {c['n_concealed_samples']} samples, "
                       f"latency p99 {c.get('latency_ms', {}).get('p99', float('nan')):.0f} ms")

    # the enhanced output covers the whole recording, and is not silence
    wav, fs = sf.read(str(out / "enhanced.wav"), dtype="float32")
    duration_s = sf.info(str(FX / "dev00.flac")).duration
    assert len(wav) / fs >= duration_s - 0.05, (len(wav) / fs, duration_s)
    assert float((wav.astype("float64") ** 2).mean()) > 1e-8
    print(f"\nnetns: {n_dropped} packets dropped by nft; enhanced {len(wav) / fs:.2f} s; "
          f"{time.monotonic() - t0:.1f} s wall\n  " + "\n  ".join(figures))
