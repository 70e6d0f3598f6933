"""Frozen dataclasses that are JAX pytrees: `flax.struct.dataclass` without flax.

hds's states (the trainer's, the simulators', the continuation's) are built from these, so a
process whose programs all come from the program cache imports neither flax nor flax.linen
(~0.15 s of a second process): `import flax` imports flax.linen. Every field is a pytree node
but a `static_field` (flax's `field(pytree_node=False)`: part of the tree's structure), and
the class is registered with `jax.tree_util.register_dataclass`, as flax registers it: its
trees, key paths and the checkpoints written from them are those of flax's."""

from __future__ import annotations

import dataclasses

import jax


def pytree_dataclass(cls):
    """`cls` as a frozen dataclass whose fields are its pytree's children (its static fields
    its structure), with `replace` (`dataclasses.replace`) as flax's structs have it."""
    data = dataclasses.dataclass(frozen=True)(cls)
    data.replace = _replace
    fields = dataclasses.fields(data)
    static = [f.name for f in fields if f.metadata.get("static")]
    children = [f.name for f in fields if not f.metadata.get("static")]
    jax.tree_util.register_dataclass(data, data_fields=children, meta_fields=static)
    return data


def static_field(**kwargs):
    """A field of a `pytree_dataclass` that is no leaf but part of the tree's structure
    (compared with ==: a change of it is another tree), as flax's `field(pytree_node=False)`."""
    return dataclasses.field(metadata={"static": True}, **kwargs)


def _replace(self, **updates):
    """A copy with the fields `updates` names replaced."""
    return dataclasses.replace(self, **updates)
