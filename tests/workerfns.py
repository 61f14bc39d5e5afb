"""Functions for ordered_map tests: they must live in a module that spawned worker processes can import."""

from __future__ import annotations

import os
import time


def slow_square(n: int) -> int:
    """n squared, taking longer for small n, so that later tasks finish first."""
    time.sleep(0.02 * (n % 3))
    return n * n


def square_or_die(n: int) -> int:
    """n squared; negative n kills the worker process outright, as a crashing decoder would."""
    if n < 0:
        os._exit(3)
    return n * n
