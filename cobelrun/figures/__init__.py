"""Paper-style plots. Functions take data frames and a matplotlib ``ax``, never live objects."""

#: plot modules by task name (``cobel plot`` picks one from the run's manifest); each has
#: ``plot_run(run_dir, out=None) -> Path`` (``plot_run(run_dir, out=None, *others)``
#: where the figure compares several run folders, e.g. Fig. 7's latent and direct groups).
#: Tasks not listed get the Fig. 6B extinction plot.
PLOTS_BY_TASK: dict[str, str] = {
    "latent_learning": "cobelrun.figures.latent",
    "two_afc": "cobelrun.figures.choice",
}
