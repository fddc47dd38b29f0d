"""The body index of `Model.link_frames` (link -> (body, pose in that body's frame)): a body of
the model (>= 0), or one of two sentinels for a link that no controlled joint moves. Both are
negative, so `body >= 0` reads "a modelled body"."""

WORLD = -1     # fixed to the root link (the world): its pose is the constant T
DROPPED = -2   # on a body the reduction dropped (beyond joints that move nothing modelled): not modelled
