"""Procedural SRN-protocol benchmark: cars and chairs built from primitives, ray-cast with embree.

Modules: ``primitives`` (parts with shading normals, materials, assembly), ``cars`` / ``car_parts`` and
``chairs`` / ``chair_parts`` (shape grammars), ``raycast`` (renderer: RGB, exact z-depth, mask), ``views``
(SRN camera placements), ``framing`` (the ``srn`` and ``legacy`` framings), ``category`` (a category's cameras,
z-range and object size), ``generate`` (the ``depthnerf synth`` driver: workers, resume, dataset card).

Entry points for other stages: :func:`~depthnerf.data.synth.generate.generate` with a
:class:`~depthnerf.data.synth.generate.SynthConfig`; for single objects (e.g. the demo),
``sample_car``/``build_car``, ``sample_chair``/``build_chair``, then ``Raycaster`` + ``render_view``.
"""
