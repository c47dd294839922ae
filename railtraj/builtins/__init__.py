"""Built-in stages. Each module is a pluggy plugin registered exactly like a third-party one."""

#: Modules registered, in order, before any entry-point plugin.
BUILTIN_PLUGINS: tuple[str, ...] = (
    "railtraj.builtins.executors",
    "railtraj.builtins.identity",
    "railtraj.builtins.gtsam_optimizer",
)
