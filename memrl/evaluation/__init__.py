"""Evaluation protocol (Table III), policies to evaluate, statistics, figures and rollouts.

* :mod:`~memrl.evaluation.protocol`: scenario seeds, the env of each initial-lane setting,
  per-episode records and the survival / goal scores.
* :mod:`~memrl.evaluation.runner`: episodes stepped in lockstep batches, in worker processes.
* :mod:`~memrl.evaluation.policies`: what can be evaluated (checkpoint, scripted, random, human).
* :mod:`~memrl.evaluation.results`: ``eval.json`` and the per-episode CSV, written and read.
* :mod:`~memrl.evaluation.periodic`: a few greedy episodes during training.
* :mod:`~memrl.evaluation.stats`: Table III with bootstrap intervals and pairwise differences.
* :mod:`~memrl.evaluation.figures`: Fig. 5 learning curves (against env steps) and mode B's stage switch.
* :mod:`~memrl.evaluation.rollouts`: Fig. 7 picture strips and MP4 videos of episodes.
"""
