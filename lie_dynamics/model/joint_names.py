"""Joints and their values: the one rule by which a message's or a trajectory's name list is read
in a model's joint order (sensor_msgs/JointState, the desired state, trajectories), and the one
rule of per-joint values (one value for every joint, or one per joint: gains, limits, friction)."""
from typing import NamedTuple, Optional

import numpy as np


class JointColumns(NamedTuple):
    index: dict                    # name -> its (first) column
    columns: Optional[np.ndarray]  # column of each joint, in the joints' order; None: a repeat or a gap
    duplicates: list               # names given more than once, sorted
    missing: list                  # joints not named, in the joints' order


def joint_columns(names, joints):
    """JointColumns of the name list `names` for `joints` (e.g. Model.joint_names). Names that are
    not joints are ignored; a repeated name or a missing joint leaves `columns` None, the caller
    says which (duplicates before missing)."""
    index = {}
    dup = set()
    for i, name in enumerate(names):
        if name in index:
            dup.add(name)
        else:
            index[name] = i
    missing = [j for j in joints if j not in index]
    columns = None if dup or missing else np.array([index[j] for j in joints], dtype=int)
    return JointColumns(index, columns, sorted(dup), missing)


def in_joint_order(values, columns):
    """A message's or a trajectory's array read in the joints' order: values[..., columns] as
    float64 (columns: JointColumns.columns)."""
    if type(values) is np.ndarray and values.dtype is _F8 and values.ndim == 1:
        return values[columns]   # one state's float64 array (every joint_states message): no conversion
    a = np.asarray(values, dtype=float)
    # a plain index for one state, 5x cheaper than with the ellipsis
    return a[columns] if a.ndim == 1 else a[..., columns]


_F8 = np.dtype(float)   # the native float64 dtype (a singleton: compared by identity)


def broadcast_joints(values, n):
    """The one rule of per-joint values: one value for every joint, or one per joint. values as
    n floats (a new array), or None when there are neither 1 nor n of them."""
    a = np.atleast_1d(np.asarray(values, dtype=float))
    if a.ndim != 1 or len(a) not in (1, n):
        return None
    return np.full(n, a[0]) if len(a) == 1 and n != 1 else a.copy()
