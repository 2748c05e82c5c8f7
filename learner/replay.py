"""An in-process uniform episode replay (FIFO eviction), for single-process training."""

from __future__ import annotations

from collections import deque

import numpy as np

from buffer_service.episode import Episode, EpisodeBatch


class EpisodeReplay:
    """Holds the latest `capacity` episodes and samples batches uniformly without replacement."""

    def __init__(self, capacity: int, rng: np.random.Generator):
        if capacity < 1:
            raise ValueError(f"replay capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.rng = rng
        self.episodes: deque[Episode] = deque(maxlen=capacity)

    def __len__(self) -> int:
        return len(self.episodes)

    def add(self, episode: Episode) -> None:
        self.episodes.append(episode)

    def can_sample(self, batch_size: int) -> bool:
        return len(self.episodes) >= batch_size

    def sample(self, batch_size: int) -> EpisodeBatch:
        idx = self.rng.choice(len(self.episodes), size=batch_size, replace=False)
        return EpisodeBatch.from_episodes([self.episodes[i] for i in idx])
