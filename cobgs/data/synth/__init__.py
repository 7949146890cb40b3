"""The synthetic scene generator (exact ground truth): :mod:`~cobgs.data.synth.scene`
(``generate_scene``, the scene folder it writes), its presets, primitives, textures, cameras and
its ray-cast renderer. ``cobgs synth`` and the ``synthetic`` dataset kind use it."""
