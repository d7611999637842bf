"""The whole frame on a torch device (issue 45): the two-scale imprint (:func:`gelsim.gel.twoscale_torch.press_batch`)
and the markers (:func:`gelsim.markers_torch.displace_batch`) batched over frames, in step with the numpy path
(the bit-exact reference and the default) within stated tolerances.

Modules: :mod:`.ops` (batched index arithmetic), :mod:`.macro` (the macro elastic solve), :mod:`.texture`
(Johnson's texture stage), :mod:`.imprint` (press_batch), :mod:`.markers`, :mod:`.frame` (protrusion to pixels:
the whole frame on the device), :mod:`.cases` (the agreement cases of the tests and benchmarks).
"""
