"""Simulated OpenMANIPULATOR-X on DYNAMIXEL XM430-W350-T servos (pure JAX).

Modules, each importing only those above it:

* ``friction``, ``servo``: the joint friction and the servo law (per-joint parameters);
* ``simulator``: one servo period of the arm (:func:`~jaxinertia.sim.simulator.step`),
  ``batched``: the same step for a batch, batch-last;
* ``sampling``: the paper's sampling protocol and the per-sample record
  (:class:`~jaxinertia.sim.sampling.Record`);
* ``params``: the default parameters fitted to the real arm (``default_sim_params``);
* ``lanes``: the lane program (pure functions: refill, steps, finish);
  ``stream``: its host runner (compilation in the background, scheduling, progress);
* ``run``: checked plans and scenarios through the stream; ``continuous``: the
  switching-load run;
* ``real_fit``: the simulator fit: the parameters fitted to the real arm's data.
"""
