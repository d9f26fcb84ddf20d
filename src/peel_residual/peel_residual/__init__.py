"""``peel residual``: close the loop with measured data (docs/residual.md).

Where the forward model is wrong on recorded tasks (the residual, one step ahead and open loop
over the planner's horizon), which physical effect it lacks (a library of named candidate terms,
selected by sparse regression with cross-validation by task), the model with that effect added
as a compensation term (:class:`~peel_model.compensated.CompensatedPredictor`), and the
error before and after on held-out tasks. Modules, in the order they run: :mod:`.tasks` (bags
-> tasks), :mod:`.data` (samples), :mod:`.predict` (predictions, term responses), :mod:`.trace`
(selection), :mod:`.structure` (what remains), :mod:`.evaluate` (errors), :mod:`.analysis`
(all of it), :mod:`.report` and :mod:`.figures` (output), :mod:`.cli` (the command).
"""
