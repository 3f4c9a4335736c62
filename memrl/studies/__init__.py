"""The pieces of ``python -m memrl.study`` (:mod:`memrl.study`).

* :mod:`~memrl.studies.grid`: the grid's train configs (Hydra's compose API), which cells to
  skip, resume or start, and training them (in this process or spawned ones).
* :mod:`~memrl.studies.extend`: ``study.extend_from``, an earlier study's finished runs copied
  in to be continued to a bigger budget.
* :mod:`~memrl.studies.evaluation`: every run, mode B's stage-1 weights and the baselines on
  the protocol, reusing finished evaluations.
* :mod:`~memrl.studies.report`: ``report.md``.
"""
