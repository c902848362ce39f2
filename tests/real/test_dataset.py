"""Tests of ``twinrl.real.dataset``: round trips, bad input, damage, SIGKILL at random moments.

The transitions come from ``_collector.transition`` (a pure function of episode id and step), the
same fake environment the kill test's subprocess records, so every test can check content exactly.
"""

from __future__ import annotations

import importlib.util
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from twinrl.real.dataset import Dataset, DatasetError, DatasetMismatch, DatasetWriter, read

HERE = Path(__file__).resolve().parent


def _load_collector():
    spec = importlib.util.spec_from_file_location("_twinrl_test_collector", HERE / "_collector.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


collector = _load_collector()
N_EPISODES = 4  # lengths 3, 8, 4, 9; endings terminated, truncated, end_episode, terminated
LENGTHS = [collector.episode_plan(ep)[0] for ep in range(N_EPISODES)]


def open_writer(path: Path, images: bool = True, **kw) -> DatasetWriter:
    return DatasetWriter(
        path,
        env="fake",
        obs_shape=collector.OBS_SHAPE,
        action_shape=collector.ACTION_SHAPE,
        image_shapes=collector.IMAGE_SHAPES if images else None,
        **kw,
    )


def step_args(ep: int, t: int, images: bool = True) -> dict:
    args = collector.transition(ep, t)
    if not images:
        del args["images"]
    return args


def write_episode(writer: DatasetWriter, images: bool = True) -> None:
    ep = writer.episode_id
    length, ending = collector.episode_plan(ep)
    for t in range(length):
        writer.add(**step_args(ep, t, images))
    if ending == "end_episode":
        writer.end_episode()


def assert_matches_collector(ds: Dataset, images: bool = True, start: int = 0) -> None:
    """Every transition in ``ds`` (from ``start``) is exactly what the collector wrote for it."""
    keys = list(zip(ds.episode_id[start:].tolist(), ds.step[start:].tolist(), strict=True))
    if not keys:
        return
    want = [collector.transition(ep, t) for ep, t in keys]
    for field in ("obs", "action", "next_obs", "reward", "terminated", "truncated"):
        np.testing.assert_array_equal(
            getattr(ds, field)[start:], np.array([w[field] for w in want]), err_msg=field
        )
    assert ds.info[start:] == [
        {k: v.item() if isinstance(v, np.generic) else v for k, v in w["info"].items()}
        for w in want
    ]
    if images:
        for key in collector.IMAGE_SHAPES:
            expected = np.stack([w["images"][key] for w in want])
            assert ds.images[key].dtype == expected.dtype
            np.testing.assert_array_equal(ds.images[key][start:], expected, err_msg=key)
    else:
        assert ds.images == {}


def record_spans(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of each record in a chunk, parsed from the documented layout, not the module."""
    spans, pos = [], 8
    while pos + 28 <= len(data):
        magic, hlen, blen, _, _ = struct.unpack_from("<4sIQII", data, pos)
        assert magic == b"TRec"
        end = pos + 28 + hlen + blen
        spans.append((pos, end))
        pos = end
    return spans


def transitions(ds: Dataset) -> list[tuple[int, int]]:
    return list(zip(ds.episode_id.tolist(), ds.step.tolist(), strict=True))


# -------------------------------------------------------------------------------------------------
# Round trips


def test_round_trip_without_images_keeps_episode_boundaries(tmp_path):
    path = tmp_path / "ds"
    with open_writer(
        path, images=False, metadata={"seed": np.int64(7), "robot": "cartpole-1"}
    ) as w:
        for _ in range(N_EPISODES):
            write_episode(w, images=False)
        w.add(**step_args(N_EPISODES, 0, images=False))  # closed mid-episode: stays incomplete

    ds = read(path)
    lengths = LENGTHS + [1]
    assert len(ds) == sum(lengths)
    assert ds.episode_starts.tolist() == np.cumsum([0] + lengths[:-1]).tolist()
    assert ds.episode_ends.tolist() == np.cumsum(lengths).tolist()
    assert ds.episode_complete.tolist() == [True] * N_EPISODES + [False]
    assert ds.step.tolist() == [t for n in lengths for t in range(n)]
    assert ds.obs.shape == (len(ds), 3) and ds.obs.dtype == np.float64
    assert ds.action.shape == (len(ds), 2) and ds.reward.dtype == np.float64
    assert ds.meta["env"] == "fake" and ds.meta["metadata"] == {"seed": 7, "robot": "cartpole-1"}
    assert ds.problems == []
    assert np.all(np.diff(ds.time) >= 0)
    assert_matches_collector(ds, images=False)

    episodes = list(ds.episodes())
    assert [e.id for e in episodes] == list(range(N_EPISODES + 1))
    assert [len(e) for e in episodes] == lengths
    assert episodes[0].terminated[-1] and not episodes[0].truncated[-1]
    assert episodes[1].truncated[-1] and not episodes[1].terminated[-1]
    # Ended by end_episode(): neither flag set, still complete.
    assert (
        not episodes[2].terminated.any()
        and not episodes[2].truncated.any()
        and episodes[2].complete
    )
    assert not episodes[-1].complete


def test_round_trip_with_images_across_chunk_rotation(tmp_path):
    path = tmp_path / "ds"
    shapes = {**collector.IMAGE_SHAPES}
    with open_writer(path, chunk_size=4, sync="episode") as w:
        assert w.episode_id == 0
        for _ in range(N_EPISODES):
            write_episode(w)
        assert w.num_added == sum(LENGTHS) and w.episode_id == N_EPISODES

    names = sorted(p.name for p in path.iterdir() if p.name.startswith("chunk-"))
    assert names == [f"chunk-00000-{i:05d}.twr" for i in range(-(-sum(LENGTHS) // 4))]
    ds = read(path)
    assert len(ds) == sum(LENGTHS) and ds.episode_complete.all()
    assert set(ds.images) == set(shapes)
    assert ds.images["rgb"].shape == (len(ds), 4, 4, 3) and ds.images["rgb"].dtype == np.uint8
    assert ds.images["depth"].dtype == np.float32 and ds.images["segmentation"].dtype == np.int32
    assert_matches_collector(ds)
    ep = list(ds.episodes())[3]
    np.testing.assert_array_equal(
        ep.images["depth"], ds.images["depth"][ds.episode_starts[3] : ds.episode_ends[3]]
    )


def test_first_episodes_is_the_datasets_prefix_episode_by_episode(tmp_path):
    path = tmp_path / "ds"
    with open_writer(path) as w:
        for _ in range(N_EPISODES):
            write_episode(w)
    ds = read(path)
    for n in (0, 1, 2, N_EPISODES, N_EPISODES + 3):
        head = ds.first_episodes(n)
        k = min(n, N_EPISODES)
        assert head.num_episodes == k and len(head) == sum(LENGTHS[:k])
        assert [e.id for e in head.episodes()] == list(range(k))
        assert len(head.info) == len(head) and head.images["rgb"].shape[0] == len(head)
        assert_matches_collector(head)


def test_camera_suffixed_image_keys(tmp_path):
    path = tmp_path / "ds"
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    with DatasetWriter(
        path, env="fake", obs_shape=(), action_shape=(1,), image_shapes={"rgb/wrist": (2, 3, 3)}
    ) as w:
        w.add(1.0, [2.0], 0.0, 2.0, True, False, images={"rgb/wrist": rgb})
    ds = read(path)
    assert ds.obs.shape == (1,) and ds.obs[0] == 1.0
    np.testing.assert_array_equal(ds.images["rgb/wrist"][0], rgb)


def test_reopening_continues_episode_ids_in_a_new_chunk(tmp_path):
    path = tmp_path / "ds"
    with open_writer(path, metadata={"run": 1}) as w:
        write_episode(w)
        w.add(**step_args(1, 0))  # episode 1 left unfinished, as by a stopped run
    with open_writer(path) as w:
        assert w.episode_id == 2 and w.session == 1
        write_episode(w)
        write_episode(w)

    ds = read(path)
    assert [e.id for e in ds.episodes()] == [0, 1, 2, 3]
    assert ds.episode_complete.tolist() == [True, False, True, True]
    assert_matches_collector(ds)
    assert {p.name for p in path.glob("chunk-*")} == {
        "chunk-00000-00000.twr",
        "chunk-00001-00000.twr",
    }
    assert ds.meta["metadata"] == {"run": 1}


@pytest.mark.parametrize(
    "change, field",
    [
        ({"env": "other"}, "env"),
        ({"obs_shape": (4,)}, "obs_shape"),
        ({"action_dtype": np.float32}, "action_dtype"),
        ({"image_shapes": {"rgb": (4, 4, 3)}}, "image_shapes"),
        ({"metadata": {"run": 2}}, "metadata"),
    ],
)
def test_reopening_with_different_settings_is_refused(tmp_path, change, field):
    path = tmp_path / "ds"
    with open_writer(path, metadata={"run": 1}) as w:
        write_episode(w)
    kw = (
        dict(env="fake", obs_shape=(3,), action_shape=(2,), image_shapes=collector.IMAGE_SHAPES)
        | change
    )
    with pytest.raises(ValueError, match=field) as e:
        DatasetWriter(path, **kw)
    if field != "metadata":  # a recorded setting: typed, naming it (the loop reads the key)
        assert isinstance(e.value, DatasetMismatch) and e.value.key == field
    assert len(read(path)) == LENGTHS[0]
    with open_writer(path) as w:  # the refused writer released the dataset
        assert w.episode_id == 1


def test_a_dataset_reads_while_it_is_written(tmp_path, monkeypatch):
    from twinrl.real.dataset import reader

    path = tmp_path / "ds"
    with open_writer(path) as w:
        write_episode(w)
        w.add(**step_args(1, 0))
        ds = read(path)
        assert len(ds) == LENGTHS[0] + 1 and ds.episode_complete.tolist() == [True, False]
        listing = reader.list_chunks(path)
    # The writer renamed the chunk closed between a reader's listing and its read.
    monkeypatch.setattr(reader, "list_chunks", lambda root: listing)
    assert len(read(path)) == LENGTHS[0] + 1


def test_a_second_writer_on_the_same_dataset_is_refused(tmp_path):
    path = tmp_path / "ds"
    with open_writer(path):
        with pytest.raises(DatasetError, match="another DatasetWriter"):
            open_writer(path)
    open_writer(path).close()


# -------------------------------------------------------------------------------------------------
# Input validation


def _bad_rgb(a):
    a["images"]["rgb"] = a["images"]["rgb"].astype(np.float32) / 255


def _missing_depth(a):
    del a["images"]["depth"]


BAD_INPUTS = {
    "obs shape": (lambda a: a.update(obs=np.zeros(4)), r"obs has shape \(4,\); expected \(3,\)"),
    "action shape": (lambda a: a.update(action=np.zeros((2, 1))), "action has shape"),
    "next_obs shape": (lambda a: a.update(next_obs=np.zeros(2)), "next_obs has shape"),
    "obs NaN": (
        lambda a: a.update(obs=np.array([0.0, np.nan, 1.0])),
        r"obs is not finite at index \(1,\)",
    ),
    "action inf": (lambda a: a.update(action=np.array([np.inf, 0.0])), "action is not finite"),
    "next_obs NaN": (
        lambda a: a.update(next_obs=np.array([np.nan, 0.0, 0.0])),
        "next_obs is not finite",
    ),
    "reward NaN": (lambda a: a.update(reward=float("nan")), "reward=nan"),
    "reward inf": (lambda a: a.update(reward=np.float32(np.inf)), "reward=inf"),
    "reward vector": (lambda a: a.update(reward=np.ones(2)), "reward="),
    "obs strings": (lambda a: a.update(obs=np.array(["a", "b", "c"])), "obs has dtype"),
    "terminated": (lambda a: a.update(terminated=2), "terminated=2"),
    "truncated": (lambda a: a.update(truncated="yes"), "truncated="),
    "info object": (lambda a: a.update(info={"x": object()}), r"info\['x'\] has type object"),
    "info key": (lambda a: a.update(info={1: 2}), "info has key 1"),
    "info list": (lambda a: a.update(info=[1]), "info has type list"),
    "rgb float": (_bad_rgb, r"images\['rgb'\] has dtype float32"),
    "depth shape": (
        lambda a: a["images"].update(depth=np.zeros((4, 5), np.float32)),
        r"images\['depth'\] has shape",
    ),
    "missing image": (_missing_depth, "images has keys"),
    "no images": (lambda a: a.pop("images"), "images has keys"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_refused_by_name_and_loses_nothing(tmp_path, case):
    corrupt, message = BAD_INPUTS[case]
    path = tmp_path / "ds"
    length = LENGTHS[1]
    with open_writer(path) as w:
        for t in range(LENGTHS[0]):  # episode 0 ends terminated
            w.add(**step_args(0, t))
        for t in range(length):
            if t == 2:
                bad = step_args(1, t)
                corrupt(bad)
                with pytest.raises(ValueError, match=message):
                    w.add(**bad)
            w.add(**step_args(1, t))
    ds = read(path)
    assert transitions(ds) == [(0, 0), (0, 1), (0, 2)] + [(1, t) for t in range(length)]
    assert ds.episode_complete.tolist() == [True, True]
    assert_matches_collector(ds)


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"sync": "always"}, "sync='always'"),
        ({"chunk_size": 0}, "chunk_size=0"),
        ({"obs_shape": (3, -1)}, "obs_shape="),
        ({"image_shapes": {"thermal": (4, 4)}}, "image_shapes key 'thermal'"),
        ({"image_shapes": {"rgb": (4, 4)}}, r"image_shapes\['rgb'\]"),
        ({"metadata": {"f": open}}, r"metadata\['f'\]"),
        ({"obs_dtype": "U3"}, "obs_dtype"),
    ],
)
def test_bad_writer_settings_are_refused_by_name(tmp_path, kw, message):
    args = dict(env="fake", obs_shape=(3,), action_shape=(2,)) | kw
    with pytest.raises(ValueError, match=message):
        DatasetWriter(tmp_path / "ds", **args)


def test_writer_refuses_a_directory_that_is_not_a_dataset(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not a twinrl dataset"):
        open_writer(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]  # left untouched


def test_writer_starts_over_a_directory_left_by_a_kill_before_meta_json(tmp_path):
    path = tmp_path / "ds"
    path.mkdir()
    (path / ".lock").touch()
    (path / "meta.json.tmp").write_text('{"format": "twinrl.re')  # killed mid-write
    with open_writer(path) as w:
        write_episode(w)
    assert len(read(path)) == LENGTHS[0]


def test_writer_is_unusable_after_close(tmp_path):
    w = open_writer(tmp_path / "ds")
    w.close()
    w.close()
    with pytest.raises(ValueError, match="closed"):
        w.add(**step_args(0, 0))


# -------------------------------------------------------------------------------------------------
# Damage


def test_missing_or_unreadable_dataset_names_the_path(tmp_path):
    for strict in (True, False):
        with pytest.raises(DatasetError, match="does not exist") as err:
            read(tmp_path / "nowhere", strict=strict)
        assert str(tmp_path / "nowhere") in str(err.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="meta.json does not exist"):
        read(tmp_path / "empty")
    path = tmp_path / "ds"
    with open_writer(path) as w:
        write_episode(w)
    (path / "meta.json").write_text('{"format": "twinrl.real.dat')
    with pytest.raises(DatasetError, match=r"meta\.json is unreadable"):
        read(path, strict=False)


@pytest.fixture
def chunked(tmp_path) -> tuple[Path, Dataset]:
    """A closed dataset of 24 transitions in 5 chunks of 5, and what it reads back as."""
    path = tmp_path / "ds"
    with open_writer(path, chunk_size=5) as w:
        for _ in range(N_EPISODES):
            write_episode(w)
    return path, read(path)


@pytest.mark.parametrize("where", ["body", "header", "prefix", "magic"])
def test_flipped_bytes_raise_naming_the_file_and_spare_the_rest(chunked, where):
    path, intact = chunked
    chunk = path / "chunk-00000-00001.twr"
    data = bytearray(chunk.read_bytes())
    start, end = record_spans(bytes(data))[1]  # transition 6: episode 1, step 3
    at = {"body": end - 5, "header": start + 40, "prefix": start + 9, "magic": start}[where]
    data[at] ^= 0x5A
    chunk.write_bytes(bytes(data))

    with pytest.raises(DatasetError, match="chunk-00000-00001.twr") as err:
        read(path)
    assert "strict=False" in str(err.value)
    ds = read(path, strict=False)
    assert ds.problems and all("chunk-00000-00001.twr" in p for p in ds.problems)
    assert transitions(ds) == transitions(intact)[:6] + transitions(intact)[7:]
    assert_matches_collector(ds)
    assert ds.episode_complete.tolist() == [True, False, True, True]  # episode 1 has a gap


@pytest.mark.parametrize("cut", ["mid-record", "footer"])
def test_truncated_closed_chunk_raises_naming_the_file(chunked, cut):
    path, intact = chunked
    chunk = path / "chunk-00000-00002.twr"
    data = chunk.read_bytes()
    spans = record_spans(data)
    size = spans[2][0] + 17 if cut == "mid-record" else spans[-1][0]  # footer is the last record
    chunk.write_bytes(data[:size])

    with pytest.raises(DatasetError, match="chunk-00000-00002.twr"):
        read(path)
    ds = read(path, strict=False)
    assert any("chunk-00000-00002.twr" in p for p in ds.problems)
    lost = 3 if cut == "mid-record" else 0  # records 2, 3, 4 of chunk 2 = transitions 12, 13, 14
    assert transitions(ds) == transitions(intact)[:12] + transitions(intact)[12 + lost :]
    assert_matches_collector(ds)


def test_deleted_chunk_is_reported(chunked):
    path, intact = chunked
    (path / "chunk-00000-00003.twr").unlink()
    with pytest.raises(DatasetError, match="missing chunk file.*chunk-00000-00003.twr"):
        read(path)
    ds = read(path, strict=False)
    assert transitions(ds) == transitions(intact)[:15] + transitions(intact)[20:]


def test_torn_tail_of_a_killed_writer_is_dropped_silently(tmp_path):
    """Every cut of an open chunk reads strictly, keeping exactly the records before the cut."""
    live, snapshot = tmp_path / "live", tmp_path / "snapshot"
    with open_writer(live) as w:
        write_episode(w)
        write_episode(w)
        for t in range(3):
            w.add(**step_args(2, t))
        # What a SIGKILL now would leave: the chunk is still .open and has no footer.
        shutil.copytree(live, snapshot)
    chunk = snapshot / "chunk-00000-00000.twr.open"
    data = chunk.read_bytes()
    spans = record_spans(data)
    n = LENGTHS[0] + LENGTHS[1] + 3
    assert len(spans) == n

    rng = np.random.default_rng(0)
    last = spans[-1][0]
    cuts = {0, 3, 8, 9, last, last + 1, last + 27, last + 28, last + 29, len(data) - 1, len(data)}
    cuts |= set(rng.integers(0, len(data), 25).tolist())
    for cut in sorted(cuts):
        chunk.write_bytes(data[:cut])
        ds = read(snapshot)
        kept = sum(end <= cut for _, end in spans)
        assert len(ds) == kept, cut
        assert transitions(ds) == transitions(read(live))[:kept]
        if 0 < kept < n:
            assert not ds.episode_complete[-1] or ds.terminated[-1] or ds.truncated[-1]
    assert_matches_collector(ds)

    # --resume after the kill: a new session, a new episode id, the torn chunk left as it was.
    chunk.write_bytes(data[: last + 30])
    with open_writer(snapshot) as w:
        assert w.episode_id == 3 and w.session == 1
        write_episode(w)
    ds = read(snapshot)
    assert [e.id for e in ds.episodes()] == [0, 1, 2, 3]
    assert ds.episode_complete.tolist() == [True, True, False, True]
    assert chunk.read_bytes() == data[: last + 30]


def test_zero_filled_tail_of_a_power_loss_is_a_torn_tail(tmp_path):
    """Power loss after unsynced appends: the file has its new length but the unwritten blocks
    read back as zeros. In an open chunk that is a torn tail (read strictly, records before kept);
    in a closed chunk, and with a record after the zeros, it is damage."""
    live = tmp_path / "live"
    with open_writer(live, sync="none") as w:
        write_episode(w)
        for t in range(3):
            w.add(**step_args(1, t))
        snapshot = tmp_path / "snapshot"
        shutil.copytree(live, snapshot)
    chunk = snapshot / "chunk-00000-00000.twr.open"
    data = chunk.read_bytes()
    spans = record_spans(data)
    whole = transitions(read(snapshot))
    for k, at in ((len(spans) - 1, spans[-1][0]),            # the last record all zeros
                  (len(spans) - 1, spans[-1][0] + 10),       # zeros from inside its prefix
                  (len(spans) - 1, spans[-1][1] - 7),        # zeros from inside its body
                  (len(spans) - 2, spans[-2][0] + 40)):      # two records, from a header on
        chunk.write_bytes(data[:at] + bytes(len(data) - at + 100))  # + zeros past the end
        ds = read(snapshot)
        assert ds.problems == [] and transitions(ds) == whole[:k], at
    # zeros in the middle, with an intact record after them, are damage
    a, b = spans[-2]
    chunk.write_bytes(data[:a] + bytes(b - a) + data[b:])
    with pytest.raises(DatasetError, match="damaged record header"):
        read(snapshot)


# -------------------------------------------------------------------------------------------------
# The acceptance criterion: SIGKILL at random moments


def _wait_for_start(out: Path, proc: subprocess.Popen, err: Path) -> int:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        text = out.read_text()
        if "\n" in text:
            first = text.split("\n", 1)[0]
            assert first.startswith("start "), first
            return int(first.split()[1])
        if proc.poll() is not None:
            pytest.fail(
                f"collector exited with {proc.returncode} before starting: {err.read_text()}"
            )
        time.sleep(0.005)
    pytest.fail("collector did not start within 30 s")


def test_sigkill_at_random_moments_loses_at_most_the_transition_in_flight(tmp_path):
    rng = np.random.default_rng(1234)
    root = tmp_path / "killed"
    syncs = (
        "transition",
        "episode",
        "none",
    )  # a kill (not a power cut) must be survived in every mode
    total, session_last_episode, stats = 0, [], []
    for kill in range(20):
        out, err = tmp_path / f"out-{kill}.txt", tmp_path / f"err-{kill}.txt"
        with open(out, "wb") as fout, open(err, "wb") as ferr:
            proc = subprocess.Popen(
                [sys.executable, str(HERE / "_collector.py"), str(root), syncs[kill % 3], "7"],
                stdout=fout,
                stderr=ferr,
            )
        try:
            first_episode = _wait_for_start(out, proc, err)
            time.sleep(rng.uniform(0.0, 0.15))
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        assert proc.returncode == -signal.SIGKILL, err.read_text()

        lines = out.read_text().split("\n")[
            1:-1
        ]  # after "start", only lines the collector finished
        reported = int(lines[-1]) if lines else 0
        ds = read(root)  # strict: a killed writer leaves no damage, only a torn tail
        recorded = len(ds) - total
        assert reported <= recorded <= reported + 1, (kill, reported, recorded)
        assert (ds.episode_id[:total] < first_episode).all() and (
            ds.episode_id[total:] >= first_episode
        ).all()
        assert_matches_collector(ds, start=total)  # earlier sessions are checked again at the end
        if recorded:
            session_last_episode.append(int(ds.episode_id[-1]))
        for e in ds.episodes():
            length = collector.episode_plan(e.id)[0]
            assert e.step.tolist() == list(range(len(e))) and len(e) <= length
            assert not e.complete or len(e) == length
            # Only the episode a kill interrupted may be incomplete.
            assert e.complete or e.id in session_last_episode, (kill, e.id)
        stats.append((reported, recorded, bool(recorded) and not ds.episode_complete[-1]))
        total = len(ds)

    print("\nkill: (completed adds reported, transitions recorded, killed mid-episode)")
    print(stats)
    recorded_per_kill = [r for _, r, _ in stats]
    print(
        f"recorded per kill: min {min(recorded_per_kill)}, max {max(recorded_per_kill)}; "
        f"total {total}"
    )
    assert total > 0 and sum(mid for _, _, mid in stats) > 0
    assert_matches_collector(read(root))
