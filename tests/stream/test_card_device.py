"""A sound card as a network device: a JACK dummy card -> ``adhoc-array device`` -> ``adhoc-array aggregate``, each
its own process, over Zenoh on 127.0.0.1."""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import soundfile as sf

RATE = 16000


def test_a_sound_card_streams_as_a_network_device(jack, bay, tmp_path):
    """adhoc-array device --input system:1 (the live-audio source) into an aggregator process, over Zenoh on
    127.0.0.1; Ctrl-C ends the device cleanly and the aggregator ends with it (--until-done)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    env = dict(os.environ, JACK_DEFAULT_SERVER=jack.name)
    cli = [sys.executable, "-m", "stream.cli"]
    before = {p.name for p in bay.client.get_ports(r"PortAudio[^:]*:in_", is_input=True)}
    agg = subprocess.Popen([*cli, "aggregate", "--out", str(tmp_path / "agg"), "--listen", ep, "--no-scouting",
                            "--array", "card", "--expect", "card0", "--until-done", "--discover-s", "30",
                            "--no-plots", "--no-status"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True)
    dev = subprocess.Popen([*cli, "device", "--name", "card0", "--input", "system:1", "--connect", ep,
                            "--no-scouting", "--array", "card", "--wait-aggregator", "30"], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        rng = np.random.default_rng(8)
        # the device's own PortAudio client: its new capture port (PortAudio numbers them from in_0)
        t_end = time.monotonic() + 60
        new: list[str] = []
        while time.monotonic() < t_end and not new:
            new = [p.name for p in bay.client.get_ports(r"PortAudio[^:]*:in_", is_input=True) if p.name not in before]
            time.sleep(0.05)
        assert new, "the device never opened its card"
        bay.rewire("bay:out_1", new[0])
        bay.play((0.1 * rng.standard_normal((30 * RATE, 1))).astype(np.float32))
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end and not (tmp_path / "agg").exists():
            time.sleep(0.1)
        time.sleep(3.0)
        dev.send_signal(signal.SIGINT)
        out, err = dev.communicate(timeout=30)
        assert dev.returncode == 0 and re.match(r"adhoc-array device card0: sent (\d+) frames", out), (out, err)
        a_out, a_err = agg.communicate(timeout=60)
        assert agg.returncode == 0, a_err[-3000:]
    finally:
        for p in (dev, agg):
            if p.poll() is None:
                p.kill()
                p.communicate()
    rep = json.loads((tmp_path / "agg" / "report.json").read_text())
    sent = int(re.match(r"adhoc-array device card0: sent (\d+) frames", out).group(1))
    d = rep["network"]["devices"]["card0"]
    assert rep["status"] == "ok" and d["n_frames"] == sent and d["n_lost_frames"] == 0 and sent > 10, (d, sent)
    assert rep["devices"][0]["facts"]["input"] == "system:1"
    assert rep["stream"]["audio_s"] >= 1.0
    y = sf.read(tmp_path / "agg" / "enhanced.wav", dtype="float32")[0]
    assert np.sqrt(np.mean(y[-RATE:] ** 2)) > 0.01          # the card's signal, not silence
