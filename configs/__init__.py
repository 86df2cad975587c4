# Installed as the package `frugalnerf_ns.configs` (see pyproject.toml) so presets ship with the plugin.
