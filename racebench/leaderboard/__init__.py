"""The leaderboard: entries (``results/leaderboard/<entry>/entry.yaml``), private seeds, verification, the site.

* :mod:`~racebench.evaluation.seeds`: the public and the private (secret-salted) evaluation seed sets;
* :mod:`~racebench.leaderboard.entries`: entry metadata, its records and its computed tier;
* :mod:`~racebench.leaderboard.verify`: re-evaluate entries and test their committed counts;
* :mod:`~racebench.leaderboard.site`: the static site.

Nothing heavy is imported here: the evaluator imports :mod:`~racebench.evaluation.seeds`.
"""
