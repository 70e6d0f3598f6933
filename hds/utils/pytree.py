"""Frozen dataclasses that are JAX pytrees: `flax.struct.dataclass` without flax.

hds's states (the trainer's, the simulators', the continuation's) are built from these, so a
process whose programs all come from the program cache imports neither flax nor flax.linen
(~0.15 s of a second process): `import flax` imports flax.linen. Every field is a pytree node,
and the class is registered with `jax.tree_util.register_dataclass`, as flax registers it: its
trees, key paths and the checkpoints written from them are those of flax's."""

from __future__ import annotations

import dataclasses

import jax


def pytree_dataclass(cls):
    """`cls` as a frozen dataclass whose fields are its pytree's children, with `replace`
    (`dataclasses.replace`) as flax's structs have it."""
    data = dataclasses.dataclass(frozen=True)(cls)
    data.replace = _replace
    names = [f.name for f in dataclasses.fields(data)]
    jax.tree_util.register_dataclass(data, data_fields=names, meta_fields=[])
    return data


def _replace(self, **updates):
    """A copy with the fields `updates` names replaced."""
    return dataclasses.replace(self, **updates)
