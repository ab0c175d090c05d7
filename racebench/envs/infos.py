"""Infos of a batch of envs: per-env dicts stacked into Gymnasium's dict of arrays (with ``_key`` masks), and
the stacked infos of several batches concatenated.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def stack_infos(infos: Sequence[dict[str, Any] | None], n: int) -> dict[str, Any]:
    """Per-env info dicts → Gymnasium's vector form: ``{key: array (n, ...), "_key": presence mask}``.

    The same arrays as ``VectorEnv._add_info`` builds env by env (nested dicts recursively, ``final_obs`` as
    an object array), except that a key whose values mix numbers and other objects is an object array whichever
    env comes first, where ``_add_info`` makes a number array if the first one holds a number (and stores
    ``None`` there as NaN or fails). ``RaceEnv``'s own infos hold no such mix (``lap_time`` is only there
    once a lap is done), so they stack alike in every vectorization mode.
    """
    keys: dict[str, None] = {}
    for info in infos:
        if info:
            keys.update(dict.fromkeys(info))
    out: dict[str, Any] = {}
    everywhere = all(info is not None and len(info) == len(keys) for info in infos)  # the usual case
    for key in keys:
        if everywhere:
            present: Sequence[int] = range(n)
            values = [info[key] for info in infos]
            mask = np.ones(n, dtype=np.bool_)
        else:
            present = [i for i, info in enumerate(infos) if info and key in info]
            values = [infos[i][key] for i in present]
            mask = np.zeros(n, dtype=np.bool_)
            mask[present] = True
        types = {type(v) for v in values}  # one set lookup per key instead of a check per value
        first = values[0]
        array: Any
        if key == "final_obs":
            array = np.full(n, None, dtype=object)
        elif types == {dict}:
            array = stack_infos([info.get(key) if info else None for info in infos], n)
        elif all(t in (int, float, bool) or issubclass(t, np.number) for t in types):
            if everywhere:  # np.array casts like _add_info's element-wise assignment into its first dtype
                out[key], out[f"_{key}"] = np.array(values, dtype=type(first)), mask
                continue
            array = np.zeros(n, dtype=type(first))
        elif all(issubclass(t, np.ndarray) for t in types):
            array = np.zeros((n, *first.shape), dtype=first.dtype)
        else:
            array = np.full(n, None, dtype=object)
        if not isinstance(array, dict):
            for i, v in zip(present, values, strict=True):
                array[i] = v
        out[key] = array
        out[f"_{key}"] = mask
    return out


def concat_infos(parts: Sequence[dict[str, Any]], sizes: Sequence[int]) -> dict[str, Any]:
    """Join the :func:`stack_infos` of consecutive slices of envs into the one of all of them."""
    if all(part.keys() == parts[0].keys() for part in parts):  # the usual case: the same keys everywhere
        out = {}
        for key, first in parts[0].items():
            if isinstance(first, dict):
                out[key] = concat_infos([part[key] for part in parts], sizes)
            else:
                out[key] = np.concatenate([part[key] for part in parts])
        return out
    keys: dict[str, None] = {}
    for part in parts:
        keys.update(dict.fromkeys(k for k in part if not (k.startswith("_") and k[1:] in part)))
    out = {}
    for key in keys:
        template = next(part[key] for part in parts if key in part)
        if isinstance(template, dict):
            out[key] = concat_infos([part.get(key, {}) for part in parts], sizes)
        else:
            arrays = []
            for part, size in zip(parts, sizes, strict=True):
                if key in part:
                    arrays.append(part[key])
                elif template.dtype == object:
                    arrays.append(np.full(size, None, dtype=object))
                else:
                    arrays.append(np.zeros((size, *template.shape[1:]), dtype=template.dtype))
            out[key] = np.concatenate(arrays)
        out[f"_{key}"] = np.concatenate(
            [part.get(f"_{key}", np.zeros(size, dtype=np.bool_)) for part, size in zip(parts, sizes, strict=True)]
        )
    return out
