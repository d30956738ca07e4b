"""The galvoscan application: the ``galvoscan`` command, bring-up, the scan client, the
evaluation (scenes, metrics, scores, report) and the simulated-rig helpers. Nothing else in
the project imports it.
"""
