"""The registry of ``skidkin`` subcommands, in the order ``--help`` lists them."""

from skidkin_ros.cli import cmd_models

ALL = [cmd_models]
