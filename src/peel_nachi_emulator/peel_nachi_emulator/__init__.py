"""peel_nachi_emulator: an emulator of the Nachi robot controller over the peeling plant.

* :mod:`.emulator`, :mod:`.faults` -- the controller emulator over PeelEnv, with faults.
* :mod:`.robot` -- the plant the emulator runs (PeelEnv in lockstep).
* :mod:`.emulator_cli` -- ``peel nachi-emulator``.
* :mod:`.bench` -- ``peel bench nachi``: STOP delay of the bridge on a force spike.
"""
