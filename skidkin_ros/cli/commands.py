"""The registry of ``skidkin`` subcommands, in the order ``--help`` lists them."""

from skidkin_ros.cli import (cmd_calibrate, cmd_demo, cmd_diagnose, cmd_effects, cmd_estimate,
                             cmd_evaluate, cmd_groundtruth, cmd_imu_study, cmd_models,
                             cmd_predict, cmd_simulate)

ALL = [cmd_demo, cmd_calibrate, cmd_evaluate, cmd_predict, cmd_diagnose, cmd_simulate,
       cmd_groundtruth, cmd_estimate, cmd_effects, cmd_imu_study, cmd_models]
