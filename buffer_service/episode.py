"""The episode record that crosses process boundaries, and its padded batch form.

Actors record whole episodes; nothing here is computed from rewards (returns, targets and
advantages belong to the learner). Arrays keep the agent axis before the feature axis.
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass, fields

import numpy as np

# dtype of every array field; the codec and the validators both read this table.
EPISODE_DTYPES: dict[str, np.dtype] = {
    "obs": np.dtype(np.float32),
    "state": np.dtype(np.float32),
    "avail_actions": np.dtype(np.uint8),
    "actions": np.dtype(np.int64),
    "reward": np.dtype(np.float32),
    "terminated": np.dtype(np.bool_),
    "filled": np.dtype(np.bool_),
}
EPISODE_ARRAYS: tuple[str, ...] = tuple(EPISODE_DTYPES)
EPISODE_SCALARS: tuple[str, ...] = ("actor_id", "episode_seq", "policy_version")
MAX_SCHEMA_SIZE = 2**31 - 1  # largest n_agents, obs_dim, ... a schema may declare


class EpisodeError(ValueError):
    """An episode or batch whose arrays do not match the schema."""


BATCH_MAPPED_MIN_BYTES = 16 * 2**20  # a batch array at least this large gets its own mapping


def off_heap_array(shape: tuple[int, ...], dtype, min_bytes: int, zeroed: bool) -> np.ndarray:
    """An array of `shape` from an anonymous mapping of its own (zero pages from the kernel,
    unmapped when the last view goes) when it holds at least `min_bytes`, else from malloc's
    heap: `np.zeros` there when `zeroed`, `np.empty` when the caller writes every element.
    What the replay's stored episodes (`buffer_service.packed.stored_buffer`) and large
    batches (`batch_zeros`) are allocated with."""
    nbytes = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    if nbytes >= min_bytes:
        try:
            flat = np.frombuffer(mmap.mmap(-1, nbytes), dtype)
            return flat.reshape(shape) if len(shape) > 1 else flat
        except OSError:  # out of mappings (vm.max_map_count): the heap will do
            pass
    return np.zeros(shape, dtype) if zeroed else np.empty(shape, dtype)


def batch_zeros(shape: tuple[int, ...], dtype) -> np.ndarray:
    """`np.zeros(shape, dtype)` for a batch's array: off the heap (`off_heap_array`) when it
    holds at least BATCH_MAPPED_MIN_BYTES.

    A padded batch of a big map is large and short-lived (bane_vs_bane, 3 seeds of 32
    episodes: 0.3-0.6 GB of observations) and each has another length. From malloc's heap,
    which a learner keeps at its peak (`run.keep_freed_memory`), each batch left the heap a
    little larger; a mapping goes back to the OS when the batch's last view goes, and the
    pages nobody writes (most of the padding) never become resident. Small batches (3m's)
    stay on the heap, where a mapping's page faults would cost more than they save.
    """
    return off_heap_array(shape, dtype, BATCH_MAPPED_MIN_BYTES, zeroed=True)


@dataclass(frozen=True)
class EpisodeSchema:
    """Sizes every episode of one environment shares.

    Attributes:
        n_agents: number of controlled agents N.
        obs_dim: per-agent observation length O.
        state_dim: global state length S.
        n_actions: per-agent discrete action count A.
        max_t: episode limit; an episode has 1..max_t transitions.
    """

    n_agents: int
    obs_dim: int
    state_dim: int
    n_actions: int
    max_t: int

    def shapes(self, t: int) -> dict[str, tuple[int, ...]]:
        """Expected array shapes of an episode with `t` transitions."""
        n, a = self.n_agents, self.n_actions
        return {
            "obs": (t + 1, n, self.obs_dim),
            "state": (t + 1, self.state_dim),
            "avail_actions": (t + 1, n, a),
            "actions": (t, n),
            "reward": (t,),
            "terminated": (t,),
            "filled": (t,),
        }

    def to_dict(self) -> dict[str, int]:
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> EpisodeSchema:
        """Schema from its dict; every size must be an int in 1..MAX_SCHEMA_SIZE (EpisodeError
        names the first field that is not: a float, inf, NaN, bool or string is refused)."""
        names = [f.name for f in fields(cls)]
        if not isinstance(d, dict) or set(d) != set(names):
            got = sorted(map(str, d)) if isinstance(d, dict) else type(d).__name__
            raise EpisodeError(f"episode schema needs exactly the keys {sorted(names)}, got {got}")
        for k in names:
            v = d[k]
            if type(v) is not int or not 1 <= v <= MAX_SCHEMA_SIZE:
                raise EpisodeError(
                    f"schema field {k!r} is {v!r}: must be an int in 1..{MAX_SCHEMA_SIZE}"
                )
        return cls(**{k: d[k] for k in names})


@dataclass(frozen=True)
class Episode:
    """One whole episode of T transitions (T >= 1).

    Shapes:
        obs [T+1, N, O] float32; state [T+1, S] float32; avail_actions [T+1, N, A] uint8;
        actions [T, N] int64; reward [T] float32; terminated [T] bool (true environment
        termination; a time-limit cut is *not* terminal and is bootstrapped); filled [T] bool
        (all True for a stored episode; False marks padding inside an EpisodeBatch).
    Scalars:
        actor_id: the recording actor; episode_seq: that actor's running episode counter (the
        pair makes inserts idempotent); policy_version: weights version that acted.
    """

    obs: np.ndarray
    state: np.ndarray
    avail_actions: np.ndarray
    actions: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    filled: np.ndarray
    actor_id: int = 0
    episode_seq: int = 0
    policy_version: int = 0

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])

    @property
    def key(self) -> tuple[int, int]:
        return (int(self.actor_id), int(self.episode_seq))

    def validate(self, schema: EpisodeSchema, state: bool = True) -> None:
        """Raise EpisodeError naming the first field that breaks `schema` (`state` False:
        the state must be empty, [T+1, 0], as in an episode stored without it)."""
        t = self.length
        if not 1 <= t <= schema.max_t:
            raise EpisodeError(f"episode length {t} outside 1..{schema.max_t}")
        shapes = schema.shapes(t)
        if not state:
            shapes["state"] = (t + 1, 0)
        for name, shape in shapes.items():
            arr = getattr(self, name)
            if not isinstance(arr, np.ndarray):
                raise EpisodeError(f"field {name!r} is {type(arr).__name__}, not a numpy array")
            if arr.dtype != EPISODE_DTYPES[name]:
                raise EpisodeError(
                    f"field {name!r} has dtype {arr.dtype}, expected {EPISODE_DTYPES[name]}"
                )
            if arr.shape != shape:
                raise EpisodeError(f"field {name!r} has shape {arr.shape}, expected {shape}")
        for name in ("obs", "state", "reward"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise EpisodeError(f"field {name!r} holds NaN or inf")
        if np.any(self.actions < 0) or np.any(self.actions >= schema.n_actions):
            raise EpisodeError(f"field 'actions' has values outside 0..{schema.n_actions - 1}")
        if np.any(self.avail_actions > 1):
            raise EpisodeError("field 'avail_actions' holds values other than 0 and 1")
        if np.any(self.terminated[:-1]):
            raise EpisodeError("field 'terminated' is set before the last transition")
        if not np.all(self.filled):
            raise EpisodeError(
                "field 'filled' must be all true in a stored episode (padding exists only "
                "inside an EpisodeBatch)"
            )
        stuck = ~self.avail_actions.any(axis=-1)  # [T+1, N]: no action available
        if np.any(stuck):
            t_, agent = (int(i) for i in np.argwhere(stuck)[0])
            raise EpisodeError(
                f"field 'avail_actions': agent {agent} has no available action at step {t_}"
            )


def _tails(ep) -> dict[str, tuple[int, ...]]:
    """Each array field's shape after its time axis, for an Episode or a PackedEpisode."""
    if isinstance(ep, Episode):
        return {name: getattr(ep, name).shape[1:] for name in EPISODE_ARRAYS}
    n, o, s, a = ep.dims
    one = {"obs": (n, o), "state": (s,), "avail_actions": (n, a), "actions": (n,)}
    return {name: one.get(name, ()) for name in EPISODE_ARRAYS}


@dataclass(frozen=True)
class EpisodeBatch:
    """Episodes padded to a common length T (the longest in the batch).

    Shapes: as `Episode` with a leading batch axis B (and, for seed-batched training, an
    ensemble axis E before it): obs [.., B, T+1, N, O], actions [.., B, T, N], filled [.., B, T]
    marks real transitions; actor_id / episode_seq / policy_version are [.., B] int64.
    """

    obs: np.ndarray
    state: np.ndarray
    avail_actions: np.ndarray
    actions: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    filled: np.ndarray
    actor_id: np.ndarray
    episode_seq: np.ndarray
    policy_version: np.ndarray

    @property
    def batch_size(self) -> int:
        return int(self.reward.shape[-2])

    @property
    def max_t(self) -> int:
        return int(self.reward.shape[-1])

    @classmethod
    def from_episodes(cls, episodes: list, pad_to: int | None = None) -> EpisodeBatch:
        """Pad and stack `episodes` (padding: zeros, avail_actions of padding = no-op only).

        `episodes` are `Episode`s or stored `buffer_service.packed.PackedEpisode`s, which are
        decoded straight into the batch's arrays (bit for bit what their `Episode` held)."""
        if not episodes:
            raise EpisodeError("cannot batch zero episodes")
        t = max(ep.length for ep in episodes) if pad_to is None else pad_to
        b = len(episodes)
        scal = {
            k: np.array([getattr(ep, k) for ep in episodes], dtype=np.int64)
            for k in EPISODE_SCALARS
        }
        dense = all(isinstance(ep, Episode) for ep in episodes)
        if dense and all(ep.length == t for ep in episodes):  # nothing to pad: one stack each
            arrays = {
                name: np.stack([getattr(ep, name) for ep in episodes]) for name in EPISODE_ARRAYS
            }
            return cls(**arrays, **scal)
        tails = _tails(episodes[0])
        out: dict[str, np.ndarray] = {}
        for name in EPISODE_ARRAYS:
            steps = t + 1 if name in ("obs", "state", "avail_actions") else t
            out[name] = batch_zeros((b, steps, *tails[name]), EPISODE_DTYPES[name])
        out["avail_actions"][..., 0] = 1
        for i, ep in enumerate(episodes):
            n = ep.length
            if n > t:
                raise EpisodeError(f"episode of length {n} does not fit pad_to={t}")
            if _tails(ep) != tails:
                raise EpisodeError(
                    f"episode {ep.key} has field shapes {_tails(ep)}, the batch's first "
                    f"{tails} (episodes stored with and without the state cannot share a batch)"
                )
            if not isinstance(ep, Episode):
                ep.write_into(out, i)
                continue
            for name in EPISODE_ARRAYS:
                arr = getattr(ep, name)
                out[name][i, : arr.shape[0]] = arr
        return cls(**out, **scal)

    @classmethod
    def from_members(cls, members: list[list[Episode]]) -> EpisodeBatch:
        """One batch per ensemble member, stacked [E, B, ...]: the same arrays as
        `stack([from_episodes(m) for m in members])`, padded once to the longest episode of
        any member and written in place (no second padding copy)."""
        sizes = {len(m) for m in members}
        if len(sizes) != 1:
            raise EpisodeError(f"members hold different numbers of episodes: {sorted(sizes)}")
        flat = [ep for m in members for ep in m]
        if not flat:
            raise EpisodeError("cannot batch zero episodes")
        whole = cls.from_episodes(flat, pad_to=max(ep.length for ep in flat))
        arrays = {f.name: getattr(whole, f.name) for f in fields(cls)}
        e, b = len(members), len(members[0])  # (not -1: a state of width 0 has no size)
        return cls(**{k: a.reshape(e, b, *a.shape[1:]) for k, a in arrays.items()})

    @classmethod
    def stack(cls, batches: list[EpisodeBatch]) -> EpisodeBatch:
        """Stack same-shaped batches along a new leading ensemble axis E."""
        t = max(b.max_t for b in batches)
        padded = [b.pad_to(t) for b in batches]
        return cls(**{f.name: np.stack([getattr(b, f.name) for b in padded]) for f in fields(cls)})

    def pad_to(self, t: int) -> EpisodeBatch:
        """Return this batch padded along the time axis to `t` transitions."""
        extra = t - self.max_t
        if extra == 0:
            return self
        if extra < 0:
            raise EpisodeError(f"cannot pad a batch of length {self.max_t} down to {t}")
        out = {}
        for f in fields(self):
            arr = getattr(self, f.name)
            if f.name in EPISODE_SCALARS:
                out[f.name] = arr
                continue
            axis = arr.ndim - (
                3
                if f.name in ("obs", "avail_actions")
                else 2
                if f.name in ("state", "actions")
                else 1
            )
            width = [(0, 0)] * arr.ndim
            width[axis] = (0, extra)
            padded = np.pad(arr, width)
            if f.name == "avail_actions":
                padded[..., -extra:, :, 0] = 1
            out[f.name] = padded
        return EpisodeBatch(**out)
