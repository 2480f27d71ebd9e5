"""Evaluation of trained simulators: metrics, training-free baselines, the evaluation tasks
(forward rollouts, inverse inference and consistency, efficiency), reports and charts.

``python evaluate.py`` composes them: :func:`rgns.evaluation.run.evaluate`.
"""
