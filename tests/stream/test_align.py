"""Coarse alignment: known start offsets of seconds are found to within a sample."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from stream.align import Aligner
from stream.offsets import JOINT_MIN_MOVE_S, OffsetWorker, coarse_offset, joint_offsets, joint_refine, recheck_offsets
from stream.messages import FrameFlag
from tests.conftest import bursty_source, delayed

FS = 8000


@pytest.mark.parametrize("offset_s", [-1.7, -0.25, 0.0, 0.4, 2.0])
def test_coarse_offset_finds_start_offsets(offset_s):
    src = bursty_source(12 * FS, sample_rate_hz=FS, seed=3)
    ref = src[2 * FS:10 * FS]
    start = int(2 * FS + offset_s * FS)
    x = src[start:start + 8 * FS] + 0.01 * np.random.default_rng(0).standard_normal(8 * FS).astype(np.float32)
    off, quality = coarse_offset(ref, x, sample_rate_hz=FS, max_offset_s=3.0)
    # x[n + off] == ref[n]  <=>  off = -(start - 2 FS)
    assert off == -(start - 2 * FS)
    assert quality > 0.5


def test_a_sentence_said_again_is_aligned_on_the_talk_not_on_its_repetition():
    """A talker who says nearly the same thing again makes the envelopes correlate at the repetition's lag too,
    over a longer overlap when the device started late; the true lag correlates better and must win (the overlap
    weighting once gave it to the repetition: a scene's device 4.7 s off)."""
    said = bursty_source(4 * FS, sample_rate_hz=FS, seed=4)
    other = bursty_source(4 * FS, sample_rate_hz=FS, seed=14)
    again = (0.8 * said + 0.2 * other).astype(np.float32)          # said again, a fifth of it different
    talk = np.concatenate([said, again, again, bursty_source(2 * FS, sample_rate_hz=FS, seed=24)])
    noise = np.random.default_rng(1).standard_normal((2, len(talk))).astype(np.float32) * 0.01
    ref = (talk + noise[0])[:8 * FS]
    late = int(1.3 * FS)                     # the device started 1.3 s after the reference
    x = (talk + noise[1])[late:late + 12 * FS]
    off, quality = coarse_offset(ref, x, sample_rate_hz=FS, max_offset_s=4.0)
    assert off == -late and quality > 0.9


def _devices_of(src, offsets, *, seed):
    """Windows of a source as devices with known offsets: ``x_d[n + offsets[d]] = ref[n]`` (plus sensor noise)."""
    rng = np.random.default_rng(seed)
    a = 3 * FS
    ref = src[a:a + 8 * FS] + 0.02 * rng.standard_normal(8 * FS).astype(np.float32)
    xs = {}
    for d, off in offsets.items():
        x = src[a - off:a - off + 12 * FS].copy()
        xs[d] = x + 0.02 * rng.standard_normal(len(x)).astype(np.float32)
    return ref, xs


def test_offsets_refined_over_every_pair_correct_one_that_is_wrong_and_keep_the_right_ones():
    """A device whose pairwise offset sits 15 ms off (a reflection's peak, say) disagrees with every other pair: the
    joint refinement puts it back within a sample; right offsets stay as they are; a disagreement below
    ``JOINT_MIN_MOVE_S`` (the fine tracker's to settle) is left alone."""
    src = bursty_source(16 * FS, sample_rate_hz=FS, seed=7)
    true = {1: 1234, 2: -567, 3: 3000, 4: 42}
    ref, xs = _devices_of(src, true, seed=8)
    wrong = {**true, 3: true[3] + int(0.015 * FS)}
    got = joint_refine(ref, {d: (xs[d], wrong[d]) for d in xs}, sample_rate_hz=FS)
    assert all(abs(got[d] - true[d]) <= 1 for d in true), (got, true)
    assert joint_refine(ref, {d: (xs[d], true[d]) for d in xs}, sample_rate_hz=FS) == true
    # through joint_offsets: the gate on the size of the move, and the devices without a clear sound left out
    small = {**true, 3: true[3] + int(0.5 * JOINT_MIN_MOVE_S * FS)}
    assert joint_offsets(ref, {d: (xs[d], small[d], 0.9) for d in xs}, sample_rate_hz=FS, min_quality=0.15) == small
    fixed = joint_offsets(ref, {d: (xs[d], wrong[d], 0.9 if d != 4 else 0.05) for d in xs}, sample_rate_hz=FS,
                          min_quality=0.15)
    assert all(abs(fixed[d] - true[d]) <= 1 for d in (1, 2, 3)) and fixed[4] == wrong[4]


def test_unrelated_signal_has_low_quality():
    a = bursty_source(6 * FS, sample_rate_hz=FS, seed=1)
    b = np.random.default_rng(5).standard_normal(6 * FS).astype(np.float32) * 0.1
    _, quality = coarse_offset(a, b, sample_rate_hz=FS, max_offset_s=2.0)
    assert quality < 0.15


def _recheck_case(n_dev=4, seconds=4.0):
    src = bursty_source(int((seconds + 1) * FS), sample_rate_hz=FS, seed=7)
    rng = np.random.default_rng(2)
    ref = src[:int(seconds * FS)]
    segments = {d: (src[40 * d:40 * d + len(ref)] + 0.01 * rng.standard_normal(len(ref))).astype(np.float32)
                for d in range(1, n_dev)}
    return ref, segments


def test_the_recheck_process_gives_the_offsets_computed_here_and_counts_its_cpu():
    """A re-check runs in a child process (so that it does not hold the stream loop's GIL): the same numbers,
    to the bit, as computed in this process, and the CPU it spent is known for the report."""
    ref, segments = _recheck_case()
    worker = OffsetWorker()
    try:
        got = worker.compute(ref, segments, sample_rate_hz=FS, max_offset_s=1.0)
        assert worker.failed is None and worker._proc is not None and worker._proc.poll() is None
        assert got == recheck_offsets(ref, segments, sample_rate_hz=FS, max_offset_s=1.0)
        assert {d: o for d, (o, _) in got.items()} == {d: -40 * d for d in segments}
        assert worker.cpu_s > 0
        assert worker.compute(ref, {}, sample_rate_hz=FS, max_offset_s=1.0) == {}
    finally:
        worker.close()
    assert worker._proc is None


def test_a_recheck_process_that_ends_is_started_again_and_one_that_breaks_falls_back_with_one_warning(caplog):
    ref, segments = _recheck_case(n_dev=3)
    expected = recheck_offsets(ref, segments, sample_rate_hz=FS, max_offset_s=1.0)
    worker = OffsetWorker()
    try:
        worker.start()
        first = worker._proc
        first.kill()
        first.wait(5)
        assert worker.compute(ref, segments, sample_rate_hz=FS, max_offset_s=1.0) == expected
        assert worker._proc is not first and worker.failed is None      # ended between re-checks: started again
        worker._proc.stdout.close()                                     # broken in the middle of one
        with caplog.at_level("WARNING", logger="stream.offsets"):
            got = worker.compute(ref, segments, sample_rate_hz=FS, max_offset_s=1.0)
            again = worker.compute(ref, segments, sample_rate_hz=FS, max_offset_s=1.0)
    finally:
        worker.close()
    assert got == again == expected                                     # computed here from then on
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "re-check" in warnings[0] and "thread" in warnings[0], warnings
    assert worker.failed is not None and worker._proc is None


def _run_aligner(devs, splits, hop=64):
    al = Aligner(len(devs), sample_rate_hz=FS, hop_samples=hop, align_window_s=3.0, max_offset_s=1.0, recheck_s=None)
    blocks = []
    pos = [0] * len(devs)
    for step in splits:
        for d, x in enumerate(devs):
            chunk = x[pos[d]:pos[d] + step]
            pos[d] += len(chunk)
            last = pos[d] >= len(x)
            blocks += al.push(d, chunk, FrameFlag.LAST if last else FrameFlag.NONE)
    blocks += al.finish()
    return al, blocks


@settings(max_examples=8, deadline=None)
@given(st.lists(st.integers(1, 3000), min_size=1, max_size=6))
def test_aligned_blocks_do_not_depend_on_the_input_split(chunk_sizes):
    src = bursty_source(6 * FS, sample_rate_hz=FS, seed=2)
    devs = [src[:5 * FS], delayed(src, -1234.0, 5 * FS)]   # device 1 starts 1234 samples later
    reps = (sum(chunk_sizes) and (5 * FS) // sum(chunk_sizes) + 1)
    al_a, a = _run_aligner(devs, chunk_sizes * reps)
    al_b, b = _run_aligner(devs, [5 * FS])
    assert al_a.offsets_samples.tolist() == al_b.offsets_samples.tolist()
    assert len(a) == len(b)
    np.testing.assert_array_equal(np.vstack([x.samples for x in a]), np.vstack([x.samples for x in b]))


def test_aligner_applies_offset_and_flags_missing_audio():
    src = bursty_source(6 * FS, sample_rate_hz=FS, seed=4)
    dev0 = src[FS:5 * FS]
    dev1 = src[FS + 800:5 * FS]     # device 1 started 800 samples later: dev1[n - 800] == dev0[n]
    al, blocks = _run_aligner([dev0, dev1], [4000] * 9)
    assert al.offsets_samples[1] == -800
    x = np.vstack([b.samples for b in blocks])
    np.testing.assert_allclose(x[800:len(dev0), 1], dev0[800:], atol=1e-6)
    # the first 800 reference samples have no device-1 audio: those blocks are invalid for device 1
    assert not blocks[0].valid[1] and blocks[0].valid[0]
    assert blocks[-1].valid[0]


def test_device_that_never_overlaps_is_left_out():
    src = bursty_source(10 * FS, sample_rate_hz=FS, seed=6)
    dev0 = src[:3 * FS]
    dev1 = np.random.default_rng(1).standard_normal(3 * FS).astype(np.float32) * 0.05
    al, blocks = _run_aligner([dev0, dev1], [1000] * 25)
    assert not al.aligned[1]
    assert any("left out" in m for m in al.messages)
    assert not any(b.valid[1] for b in blocks)


def test_a_reference_that_joins_late_is_aligned_on_its_audio_not_its_lead():
    """Over the network the reference may be heard seconds after the others: its lead is flagged zeros (GAP).
    The first alignment takes its window from the reference's first audio, so the offset is still found."""
    src = bursty_source(12 * FS, sample_rate_hz=FS, seed=6)
    lead = 4 * FS
    al = Aligner(2, sample_rate_hz=FS, hop_samples=64, align_window_s=3.0, max_offset_s=1.0, recheck_s=None,
                 deadline_s=None)
    blocks = list(al.push(0, np.zeros(lead, np.float32), FrameFlag.GAP))
    blocks += al.push(1, delayed(src, -300.0, 10 * FS), FrameFlag.NONE)   # device 1 starts 300 samples later
    assert not al.ready and not blocks                  # waiting for the reference's audio
    blocks += al.push(0, np.r_[np.zeros(0, np.float32), src[lead:10 * FS]], FrameFlag.NONE)
    assert al.ready and al.aligned.all() and al.quality[1] > 0.5
    assert al.offsets_samples[1] == -300


def test_a_device_with_a_new_clock_leaves_the_beam_until_a_recheck_finds_it():
    """NEW_CLOCK (the device restarted): its old offset means nothing, so it is left out of the beamformer,
    and the next re-check that hears it well aligns it again at its new offset."""
    src = bursty_source(30 * FS, sample_rate_hz=FS, seed=7)
    src = src + 1e-3 * np.random.default_rng(7).standard_normal(len(src)).astype(np.float32)   # a room, not zeros
    al = Aligner(2, sample_rate_hz=FS, hop_samples=64, align_window_s=3.0, max_offset_s=1.0, recheck_s=2.0,
                 deadline_s=None)
    list(al.push(0, src[:30 * FS], FrameFlag.NONE))
    list(al.push(1, src[:10 * FS], FrameFlag.NONE))              # aligned at offset 0 for 10 s
    assert al.ready and al.offsets_samples[1] == 0
    # it restarts: its next sample is the room 0.2 s later than its old clock says (a new offset of +1600)
    blocks = list(al.push(1, src[10 * FS + 1600:29 * FS], FrameFlag.NEW_CLOCK))
    assert any("Device 1 restarted with a new clock" in m for m in al.messages)
    after = [b for b in blocks if b.first_sample >= 10 * FS]
    assert not after[0].valid[1]                                 # out of the beam at once
    assert al.offsets_samples[1] == -1600 and after[-1].valid[1]  # found again by a re-check


def test_a_reference_that_hears_only_noise_gives_way_to_the_device_the_others_share_their_sound_with():
    """Device 0 records only noise: the offsets are measured against device 1 instead (one sentence says so),
    device 0 is left out, and the re-checks measure against device 1 too (device 2 restarts with a new clock
    and is found again)."""
    src = bursty_source(30 * FS, sample_rate_hz=FS, seed=8)
    src = src + 1e-3 * np.random.default_rng(8).standard_normal(len(src)).astype(np.float32)
    noise = 0.05 * np.random.default_rng(9).standard_normal(30 * FS).astype(np.float32)
    al = Aligner(3, sample_rate_hz=FS, hop_samples=64, align_window_s=3.0, max_offset_s=1.0, recheck_s=2.0,
                 deadline_s=None)
    list(al.push(0, noise, FrameFlag.NONE))
    list(al.push(1, src[:29 * FS], FrameFlag.NONE))
    list(al.push(2, src[500:10 * FS], FrameFlag.NONE))      # device 2 started 500 samples later
    assert al.ready and al.pivot == 1
    assert al.aligned.tolist() == [False, True, True]
    assert al.offsets_samples[1] == 0 and al.offsets_samples[2] == -500
    assert any("measured against device 1" in m for m in al.messages)
    blocks = list(al.push(2, src[10 * FS + 1600:29 * FS], FrameFlag.NEW_CLOCK))   # 0.1 s on, its new clock
    assert not any(b.valid[0] for b in blocks)
    assert al.offsets_samples[2] == -2100 and blocks[-1].valid[2]   # found again against device 1


def test_a_silent_reference_gives_way_too():
    src = bursty_source(8 * FS, sample_rate_hz=FS, seed=9)
    src = src + 1e-3 * np.random.default_rng(9).standard_normal(len(src)).astype(np.float32)   # a room, not zeros
    al, blocks = _run_aligner([np.zeros(6 * FS, np.float32), src[:6 * FS], src[300:6 * FS]], [1000] * 40)
    assert al.pivot == 1 and al.aligned.tolist() == [False, True, True] and al.offsets_samples[2] == -300
    valid = np.array([b.valid for b in blocks])
    assert not valid[:, 0].any() and valid[:, 1:].mean() > 0.95
