"""Constants of the tick's select stage shared by its numpy tests (selection.py) and their Warp kernels
(select_kernels.py): here, so the kernels need not import selection.py, which imports them."""

INSIDE_CHANGE = 0.5  # occlusion_change of a point inside a mover's bounding sphere now or before: half its
# hemisphere changed, as a deforming mover's own points count (the tick's _mover_change)
