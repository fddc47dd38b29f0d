"""Pickling a Model: a model built in another process comes back whole and fast.

Pickling and deepcopy carry the constant data, and which arrays are read-only (numpy's pickles
come back writeable). The per-link tables travel as a few stacked arrays: thousands of small
arrays would take the unpickling process's interpreter lock for tens of ms. (The kernels and
their caches live in codegen, keyed by the object, and are rebuilt where the copy is used.)
"""
import numpy as np

PER_LINK = ('_places', '_link_inertias', 'link_frames')   # link -> tuple of values and small arrays


def _pack(table):
    """(keys, columns) of a dict of equal-length tuples; a column of arrays of one shape and
    dtype is stacked into one array, with whether they were all read-only (pickles and copies
    of arrays come back writeable)."""
    columns = []
    for col in zip(*table.values()):
        if all(isinstance(a, np.ndarray) for a in col) and len({(a.shape, a.dtype) for a in col}) == 1:
            columns.append((np.stack(col), not any(a.flags.writeable for a in col)))
        else:
            columns.append((list(col), None))
    return list(table), columns


def _unpack(packed):
    keys, columns = packed
    for values, read_only in columns:
        if read_only:
            values.flags.writeable = False
    return dict(zip(keys, zip(*[list(values) for values, _ in columns])))


class Pickled:
    """__getstate__ / __setstate__ of `model.Model` (a mixin)."""

    def __getstate__(self):
        """The model's state for pickle and deepcopy (module docstring)."""
        state = dict(self.__dict__)
        state['_read_only'] = [k for k, v in state.items() if isinstance(v, np.ndarray) and not v.flags.writeable]
        for k in PER_LINK:
            state[k] = _pack(state[k])
        return state

    def __setstate__(self, state):
        read_only = state.pop('_read_only', ())
        for k in PER_LINK:
            state[k] = _unpack(state[k])
        self.__dict__.update(state)
        for k in read_only:
            getattr(self, k).flags.writeable = False
