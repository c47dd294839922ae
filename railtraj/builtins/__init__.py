"""Built-in stages. Each module is a pluggy plugin registered exactly like a third-party one."""

#: Modules registered, in order, before any entry-point plugin.
BUILTIN_PLUGINS: tuple[str, ...] = (
    "railtraj.builtins.executors",
    "railtraj.builtins.dask_executor",
    "railtraj.builtins.identity",
    "railtraj.builtins.gtsam_optimizer",
    "railtraj.builtins.spline_optimizer",
    "railtraj.builtins.median_optimizer",
    "railtraj.builtins.iss",
    "railtraj.builtins.harris3d",
    "railtraj.builtins.fpfh",
    "railtraj.builtins.none_descriptor",
    "railtraj.builtins.mutual_nn",
    "railtraj.builtins.pair_voting",
    "railtraj.builtins.icp",
)
