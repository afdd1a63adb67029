"""The registry of ``skidkin`` subcommands, in the order ``--help`` lists them."""

from skidkin_ros.cli import (cmd_calibrate, cmd_demo, cmd_diagnose, cmd_evaluate,
                             cmd_groundtruth, cmd_models, cmd_predict, cmd_simulate)

# The product's commands only; the studies' commands live in the lab (python -m lab.cli).
ALL = [cmd_demo, cmd_calibrate, cmd_evaluate, cmd_predict, cmd_diagnose, cmd_simulate,
       cmd_groundtruth, cmd_models]
