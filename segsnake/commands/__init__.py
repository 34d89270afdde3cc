"""Sub-commands of the ``segsnake`` CLI; each module has ``add_parser`` and sets ``func``."""
