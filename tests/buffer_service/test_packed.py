"""The packed episode form: exact (batches bit-identical to dense ones), compact, checked."""

from __future__ import annotations

import dataclasses
import mmap

import numpy as np
import pytest

from buffer_service.episode import Episode, EpisodeBatch, EpisodeError, EpisodeSchema
from buffer_service.packed import MAPPED_MIN_BYTES, PackedEpisode, dense_bytes
from tests.buffer_service.conftest import SCHEMA, make_episode

BIG = EpisodeSchema(n_agents=6, obs_dim=40, state_dim=30, n_actions=9, max_t=60)


def smac_like(seq: int, t: int, schema: EpisodeSchema = BIG) -> Episode:
    """An episode shaped like SMAC's: dead agents' rows all zero, one-hot flags of exactly
    1.0, other features any float (-0.0, denormals and 1.0 - ulp included)."""
    rng = np.random.default_rng(seq)
    n, o = schema.n_agents, schema.obs_dim
    obs = rng.standard_normal((t + 1, n, o)).astype(np.float32)
    obs[rng.random((t + 1, n, o)) < 0.6] = 0.0
    obs[rng.random((t + 1, n, o)) < 0.2] = 1.0
    obs[:, :, 0] = -0.0
    obs[:, :, 1] = np.float32(1e-40)  # denormal
    obs[:, :, 2] = np.nextafter(np.float32(1.0), np.float32(0.0))
    dead = rng.random((t + 1, n)) < 0.5
    obs[dead] = 0.0
    state = rng.standard_normal((t + 1, schema.state_dim)).astype(np.float32)
    state[:, ::3] = 0.0
    avail = (rng.random((t + 1, n, schema.n_actions)) < 0.5).astype(np.uint8)
    avail[..., 0] = 1
    ep = make_episode(0, seq, t, schema)
    return dataclasses.replace(ep, obs=obs, state=state, avail_actions=avail)


def _same(a, b) -> None:
    for f in dataclasses.fields(EpisodeBatch):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert x.dtype == y.dtype and x.shape == y.shape, f.name
        assert x.tobytes() == y.tobytes(), f.name  # bit for bit (-0.0 is not 0.0 here)


def test_batches_of_packed_episodes_are_bit_identical_to_dense_ones():
    eps = [smac_like(i, t) for i, t in enumerate([3, 17, 60, 1, 25, 60])]
    packed = [PackedEpisode.pack(ep) for ep in eps]
    for p in packed:
        p.validate(BIG)
    _same(EpisodeBatch.from_episodes(packed), EpisodeBatch.from_episodes(eps))
    _same(EpisodeBatch.from_episodes(packed, pad_to=70), EpisodeBatch.from_episodes(eps, 70))
    members = [eps[:3], eps[3:]]
    packed_members = [packed[:3], packed[3:]]
    _same(EpisodeBatch.from_members(packed_members), EpisodeBatch.from_members(members))
    # a mixed batch (old dense episodes beside packed ones) is the same too
    _same(EpisodeBatch.from_episodes([eps[0], packed[1]]), EpisodeBatch.from_episodes(eps[:2]))


def _numpy_reference_pack(ep: Episode, state: bool = True) -> bytes:
    """The numpy encoding `PackedEpisode.pack` used before its numba kernels: the layout of
    the module docstring, built from numpy passes and joined."""

    def floats(a):
        bits = np.ascontiguousarray(a, np.float32).view(np.uint32)
        live = bits.any(axis=1)
        nz = bits[live] != 0
        nzvals = bits[live][nz]
        ones = nzvals == np.float32(1.0).view(np.uint32)
        flags = live if a.shape[1] else live[:0]
        return nzvals[~ones], [np.packbits(flags), np.packbits(nz), np.packbits(ones)]

    st = ep.state if state else ep.state[:, :0]
    ov, obits = floats(ep.obs.reshape(-1, ep.obs.shape[2]))
    sv, sbits = floats(st)
    a = ep.avail_actions.shape[2]
    actions = ep.actions.astype(np.uint8 if a <= 256 else np.dtype("<i4"))
    parts = [ov, sv, np.asarray(ep.reward, np.float32), actions, *obits, *sbits]
    parts.append(np.packbits(ep.avail_actions.reshape(-1)))
    return b"".join(np.ascontiguousarray(p).tobytes() for p in parts)


@pytest.mark.parametrize("state", [True, False])
def test_pack_writes_the_same_bytes_as_the_numpy_encoding_it_replaced(state):
    many = EpisodeSchema(n_agents=2, obs_dim=5, state_dim=3, n_actions=300, max_t=20)
    eps = [smac_like(i, t) for i, t in enumerate([1, 2, 7, 17, 60])]
    eps += [smac_like(9, 13, many), make_episode(0, 1, 5, BIG)]  # int32 actions; all-zero obs
    all_dead = smac_like(10, 9)
    eps.append(dataclasses.replace(all_dead, obs=np.zeros_like(all_dead.obs)))
    for ep in eps:
        assert PackedEpisode.pack(ep, state).data.tobytes() == _numpy_reference_pack(ep, state)


def test_without_the_state_everything_else_is_unchanged():
    eps = [smac_like(i, t) for i, t in enumerate([5, 9])]
    bare = [PackedEpisode.pack(ep, state=False) for ep in eps]
    assert bare[0].has_state is False
    for p in bare:
        p.validate(BIG)
    batch, dense = EpisodeBatch.from_episodes(bare), EpisodeBatch.from_episodes(eps)
    assert batch.state.shape == (2, 10, 0)
    for name in ("obs", "avail_actions", "actions", "reward", "terminated", "filled"):
        assert getattr(batch, name).tobytes() == getattr(dense, name).tobytes(), name
    assert PackedEpisode.pack(PackedEpisode.pack(eps[0]), state=False).data.tobytes() == (
        bare[0].data.tobytes()
    )
    members = EpisodeBatch.from_members([bare[:1], bare[1:]])
    assert members.state.shape == (2, 1, 10, 0)
    with pytest.raises(EpisodeError, match="with and without the state"):
        EpisodeBatch.from_episodes([bare[0], PackedEpisode.pack(eps[1])])


def test_packed_is_much_smaller_on_sparse_observations():
    eps = [smac_like(i, 40) for i in range(4)]
    dense = sum(dense_bytes(ep) for ep in eps)
    packed = sum(PackedEpisode.pack(ep, state=False).nbytes for ep in eps)
    assert packed < dense / 3, (packed, dense)


def test_what_cannot_be_packed_or_does_not_fit_the_schema_is_refused():
    ep = make_episode(0, 0, t=4)
    with pytest.raises(EpisodeError, match="filled"):
        PackedEpisode.pack(dataclasses.replace(ep, filled=np.zeros(4, bool)))
    early = np.array([True, False, False, True])
    with pytest.raises(EpisodeError, match="terminated"):
        PackedEpisode.pack(dataclasses.replace(ep, terminated=early))
    with pytest.raises(EpisodeError, match="avail_actions"):
        PackedEpisode.pack(dataclasses.replace(ep, avail_actions=ep.avail_actions * 2))
    wraps = ep.avail_actions.astype(np.int64) * 256  # 0 once cast to uint8
    with pytest.raises(EpisodeError, match="avail_actions"):
        PackedEpisode.pack(dataclasses.replace(ep, avail_actions=wraps))
    nan = ep.obs.copy()
    nan[1, 1, 1] = np.nan
    with pytest.raises(EpisodeError, match="NaN"):
        PackedEpisode.pack(dataclasses.replace(ep, obs=nan)).validate(SCHEMA)
    other = EpisodeSchema(n_agents=4, obs_dim=5, state_dim=7, n_actions=4, max_t=10)
    with pytest.raises(EpisodeError, match="shape"):
        PackedEpisode.pack(ep).validate(other)


@pytest.mark.parametrize(
    "field, shape",
    [
        ("obs", (5, SCHEMA.n_agents + 1, SCHEMA.obs_dim)),  # more agents than avail_actions
        ("obs", (5, SCHEMA.n_agents * SCHEMA.obs_dim)),
        ("state", (6, SCHEMA.state_dim)),
        ("avail_actions", (5, SCHEMA.n_agents - 1, SCHEMA.n_actions)),
        ("actions", (4, SCHEMA.n_agents + 2)),
        ("reward", (3,)),
        ("terminated", (5,)),
        ("filled", (4, 1)),
    ],
)
def test_arrays_whose_shapes_disagree_are_refused_before_packing(field, shape):
    # an episode from the wire (protocol 1) is packed by the server: nothing may be
    # written by its shapes until they agree with each other
    ep = make_episode(0, 0, t=4)
    bad = np.zeros(shape, getattr(ep, field).dtype)
    with pytest.raises(EpisodeError, match="shape") as e:
        PackedEpisode.pack(dataclasses.replace(ep, **{field: bad}))
    assert field in str(e.value) or "avail_actions" in str(e.value)  # the first disagreeing


def _corrupt(p: PackedEpisode, section: str, value, dtype=np.uint8) -> PackedEpisode:
    """`p` with the first element of one section of its buffer set to `value` (as a
    hostile client could send it: the packed form, not an Episode)."""
    data = p.data.copy()
    off, _ = p.layout[section]
    data[off : off + np.dtype(dtype).itemsize].view(dtype)[0] = value
    return dataclasses.replace(p, data=data)


@pytest.mark.parametrize(
    "section,value,dtype,match",
    [
        ("obs_values", np.inf, np.float32, "'obs' holds NaN or inf"),
        ("state_values", np.nan, np.float32, "'state' holds NaN or inf"),
        ("reward", -np.inf, np.float32, "'reward' holds NaN or inf"),
        ("actions", 9, np.uint8, "'actions' has values outside 0..8"),
        ("avail", 0, np.uint16, "agent 0 has no available action at step 0"),
    ],
)
def test_packed_checks_refuse_what_the_dense_checks_refuse(section, value, dtype, match):
    """The server validates inserts on the packed form without decoding them: each bad
    value gets the same error as the decoded episode gets from `Episode.validate`."""
    bad = _corrupt(PackedEpisode.pack(smac_like(3, 20)), section, value, dtype)
    for check in (lambda: bad.validate(BIG), lambda: bad.unpack().validate(BIG)):
        with pytest.raises(EpisodeError, match=match):
            check()


def test_decoding_bits_that_disagree_with_their_counts_is_refused_not_read_past():
    # check_layout refuses such an episode on every way in; the decoder checks again
    p = PackedEpisode.pack(smac_like(3, 20))
    lay = p.layout
    for section in ("obs_nonzero", "obs_live", "state_nonzero"):  # (every state row is live)
        data = p.data.copy()
        off, size = lay[section]
        data[off : off + size] = 0xFF
        bad = dataclasses.replace(p, data=data)
        with pytest.raises(EpisodeError, match="disagree"):
            bad.unpack()


def _numpy_reference_check(p: PackedEpisode, schema: EpisodeSchema) -> str | None:
    """The first error of `check_layout` then `validate_contents`, as the numpy code that the
    compiled checks replaced computed it (None: accepted)."""
    lay = p.layout
    if p.data.size != sum(size for _, size in lay.values()):
        return "data holds"
    names = [f"{x}_{k}" for x in ("obs", "state") for k in ("live", "nonzero", "ones")]
    expect = p._bit_counts(p.obs_counts) + p._bit_counts(p.state_counts)
    for name, (set_bits, used) in zip(names, expect, strict=True):
        off, size = lay[name]
        pad = -used % 8
        total = int(np.unpackbits(p.data[off : off + size]).sum())
        if total != set_bits or (pad and size and int(p.data[off + size - 1]) & ((1 << pad) - 1)):
            prefix, part = name.split("_")
            return f"packed {prefix}: {part} bits disagree with its counts"
    t, (n, _, _, a) = p.length, p.dims
    for name, section in (("obs", "obs_values"), ("state", "state_values"), ("reward", "reward")):
        if not np.all(np.isfinite(p._view(section, np.float32, lay))):
            return f"field {name!r} holds NaN or inf"
    actions = p._view("actions", p.action_dtype, lay)
    if actions.size and (int(actions.min()) < 0 or int(actions.max()) >= schema.n_actions):
        return f"field 'actions' has values outside 0..{schema.n_actions - 1}"
    avail = np.unpackbits(p._view("avail", layout=lay), count=(t + 1) * n * a)
    stuck = ~avail.reshape(t + 1, n, a).any(axis=-1)
    if np.any(stuck):
        step, agent = (int(i) for i in np.argwhere(stuck)[0])
        return f"field 'avail_actions': agent {agent} has no available action at step {step}"
    return None


def test_the_compiled_checks_agree_with_the_numpy_checks_they_replaced():
    """Random byte flips in every section of packed episodes (narrow and int32 actions, with
    and without the state, sparse and all-zero observations): `check_layout` and
    `validate_contents` accept exactly what the numpy checks accepted, with the same error."""
    wide = EpisodeSchema(n_agents=2, obs_dim=5, state_dim=3, n_actions=300, max_t=20)
    cases = [(PackedEpisode.pack(smac_like(i, t)), BIG) for i, t in enumerate([1, 7, 33])]
    cases.append((PackedEpisode.pack(smac_like(5, 20), state=False), BIG))
    cases.append((PackedEpisode.pack(smac_like(6, 13, wide)), wide))
    all_dead = smac_like(7, 9)
    cases.append((PackedEpisode.pack(dataclasses.replace(all_dead, obs=0 * all_dead.obs)), BIG))
    huge = smac_like(8, 5)  # the largest finite floats (exponent bits one short of inf's)
    huge.obs[:, :, 3:5] = np.finfo(np.float32).max * np.array([1, -1], np.float32)
    huge.reward[:] = np.float32(2.0**127)
    cases.append((PackedEpisode.pack(huge), BIG))
    rng = np.random.default_rng(0)
    verdicts = set()
    for p, schema in cases:
        assert _numpy_reference_check(p, schema) is None
        p.validate(schema)
        for section, (off, size) in p.layout.items():
            if not size:
                continue
            for trial in range(16):
                data = p.data.copy()
                for _ in range(rng.integers(1, 4)):  # one to three flipped bytes
                    data[off + rng.integers(size)] ^= rng.integers(1, 256, dtype=np.uint8)
                if trial % 2 and section in ("obs_values", "state_values", "reward"):
                    # (random flips seldom make a NaN or inf: also write one somewhere)
                    i = 4 * rng.integers(size // 4)
                    poison = rng.choice([np.inf, -np.inf, np.nan]).astype(np.float32)
                    data[off + i : off + i + 4] = np.frombuffer(poison.tobytes(), np.uint8)
                if trial % 2 and section == "avail":  # no action available somewhere
                    i = rng.integers(size)
                    data[off + i : off + i + 2] = 0
                bad = dataclasses.replace(p, data=data)
                want = _numpy_reference_check(bad, schema)
                try:
                    bad.check_layout()
                    bad.validate_contents(schema)
                    got = None
                except EpisodeError as e:
                    got = str(e)
                assert got == want, (section, got, want)
                verdicts.add(want.split(":")[0].split(" holds")[0] if want else None)
    # the flips reached every kind of check, and some flips stay valid (values, actions)
    assert {None, "field 'obs'", "field 'state'", "field 'reward'", "packed obs"} <= verdicts
    assert {"packed state", "field 'avail_actions'"} <= verdicts
    assert any(v and "actions" in v for v in verdicts), verdicts


def test_packed_length_and_layout_bits_are_checked():
    p = PackedEpisode.pack(smac_like(4, 60))
    with pytest.raises(EpisodeError, match=r"length 60 outside 1\.\.59"):
        p.validate(dataclasses.replace(BIG, max_t=59))
    # a set bit in the padding after a section's last used bit (nothing decodes it, but a
    # stored episode has exactly one packed form)
    c = p.obs_counts
    assert c.nonzero % 8, "the test needs a section with padding bits"
    off, size = p.layout["obs_ones"]
    data = p.data.copy()
    data[off + size - 1] |= 1
    with pytest.raises(EpisodeError, match="obs: ones bits disagree"):
        dataclasses.replace(p, data=data).check_layout()
    data = p.data.copy()
    off, _ = p.layout["obs_live"]
    data[off] ^= 0x80  # one more (or one fewer) live row than counted
    with pytest.raises(EpisodeError, match="obs: live bits disagree"):
        dataclasses.replace(p, data=data).check_layout()


def test_counts_asking_for_more_bytes_than_int64_holds_are_refused_by_name():
    """Counts within the wire's bounds (each below 2**40) whose sections would need more
    than 2**63 bytes: refused as a layout error (it used to escape as an OverflowError,
    which the server met with a dropped connection and a traceback in its log)."""
    from buffer_service import codec
    from buffer_service.codec import CodecError

    wire = codec.episode_to_wire(PackedEpisode.pack(smac_like(1, 5)))
    n, o = 2**38, 2**39  # live rows x features = 2**78 nonzero bits
    wire.update(dims=[n, o, 0, 2], length=1)
    wire.update(obs_counts=[2 * n, o, 2 * n, 2 * n, 0], state_counts=[2, 0, 0, 0, 0])
    with pytest.raises(CodecError, match="its counts need"):
        codec.episode_from_wire(wire)


def test_large_episodes_are_stored_outside_the_heap_and_copied_out_of_frames():
    wide = EpisodeSchema(n_agents=24, obs_dim=80, state_dim=30, n_actions=9, max_t=60)
    ep = PackedEpisode.pack(smac_like(1, 60, wide))
    assert ep.data.nbytes >= MAPPED_MIN_BYTES
    assert PackedEpisode.pack(smac_like(1, 5)).data.base is None  # small: on the heap
    assert isinstance(ep.data.base.obj, mmap.mmap)  # its own mapping (see stored_buffer)
    assert ep.nbytes % 4096 == 900 % 4096  # whole pages, plus the objects' overhead
    view = dataclasses.replace(ep, data=np.frombuffer(ep.data.tobytes(), np.uint8))
    owned = view.owned()
    assert not np.shares_memory(owned.data, view.data)
    assert owned.data.tobytes() == ep.data.tobytes()


def _storage_with(tmp_path, episodes, wire) -> None:
    """A buffer folder whose snapshot and log hold `episodes` written with `wire` (the
    episode map of some version: protocol 1's dense map, or a packed one)."""
    from buffer_service import codec, records, snapshots
    from buffer_service.config import BufferConfig
    from buffer_service.state import BufferState
    from buffer_service.storage import Storage
    from tests.buffer_service.conftest import table

    cfg = BufferConfig(tables=(table("replay", "replay", capacity=100),), schema=SCHEMA)
    state, storage = BufferState(cfg), Storage(str(tmp_path), tables=cfg.tables)
    storage.restore(state)
    for ep in episodes[:2]:
        state.insert(ep, ["replay"])
    real = snapshots.codec.episode_to_wire
    snapshots.codec.episode_to_wire = lambda p: wire(p.unpack())  # as an older build wrote
    try:
        storage.snapshot(state)
    finally:
        snapshots.codec.episode_to_wire = real
    for ep in episodes[2:]:
        body = codec.pack({"op": "insert", "v": 1, "episodes": [wire(ep)]})
        storage.append_insert(["replay"], body)
    storage.sync()
    storage.close()
    assert records.scan_file(storage.path("log", storage.gen)).records


def _restore(tmp_path, **kw):
    from buffer_service.config import BufferConfig
    from buffer_service.state import BufferState
    from buffer_service.storage import Storage
    from tests.buffer_service.conftest import table

    cfg = BufferConfig(tables=(table("replay", "replay", capacity=100),), schema=SCHEMA, **kw)
    state = BufferState(cfg)
    Storage(str(tmp_path), tables=cfg.tables, read_only=True).restore(state)
    return state


def test_logs_and_snapshots_written_before_packing_are_read_and_packed(tmp_path):
    from buffer_service import codec

    eps = [make_episode(0, i, t=4) for i in range(4)]
    _storage_with(tmp_path, eps, codec.dense_to_wire)
    state = _restore(tmp_path, store_state=False)
    assert sorted(state.episodes) == [(0, i) for i in range(4)]
    for ep in eps:
        got = state.episodes[ep.key]
        assert isinstance(got, PackedEpisode) and not got.has_state  # dropped on reading
        for name in ("obs", "avail_actions", "actions", "reward", "terminated"):
            assert getattr(got, name).tobytes() == getattr(ep, name).tobytes(), name


def test_a_log_of_an_unknown_packing_is_refused_by_name(tmp_path):
    from buffer_service import codec
    from buffer_service.storage import StorageError

    def newer(ep: Episode, to_wire=codec.episode_to_wire) -> dict:  # (bound before patching)
        return dict(to_wire(ep), packing=2)

    _storage_with(tmp_path, [make_episode(0, i, t=4) for i in range(3)], newer)
    with pytest.raises(StorageError, match="episode packing 2 is not one this build reads"):
        _restore(tmp_path)


def test_warm_kernels_loads_what_an_insert_uses():
    """`credit buffer serve` calls `warm_kernels` before it listens; afterwards the checks
    of a packed insert (on a read-only frame or an owned buffer) find every kernel they call
    loaded for their argument types (in a fresh process: nothing else warmed it)."""
    import subprocess
    import sys

    code = """
import dataclasses, numpy as np
from buffer_service import pack_kernels as K
from buffer_service.packed import PackedEpisode, warm_kernels
from tests.buffer_service.test_packed import BIG, smac_like
names = ("counts", "fill", "check_bits", "check_values")
def loaded():
    return {k: len(getattr(K, k).signatures) for k in names}
warm_kernels()
warm = loaded()
assert all(warm.values()), warm
p = PackedEpisode.pack(smac_like(1, 30))
framed = dataclasses.replace(p, data=np.frombuffer(p.data.tobytes(), np.uint8))
for q in (framed, p):
    q.validate(BIG)
assert loaded() == warm, (warm, loaded())
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
