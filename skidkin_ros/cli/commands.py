"""The registry of ``skidkin`` subcommands, in the order ``--help`` lists them."""

from skidkin_ros.cli import cmd_groundtruth, cmd_models, cmd_simulate

ALL = [cmd_simulate, cmd_groundtruth, cmd_models]
