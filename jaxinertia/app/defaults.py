"""The library's defaults that the parsers use and ``--help`` shows, written out here so
that parsing a command line imports no JAX (the modules that own them do).

Each value is the library's own: ``tests/test_reliability.py`` checks every one against
the module that owns it (``training.TrainConfig``, ``objects.known_names``, ...), so a
change there that is not made here fails the tests.
"""

from __future__ import annotations

__all__ = ["ARM_NAMES", "BUS_RETRIES", "DEFAULT_ARM", "FINETUNE", "GRIPPER_ID", "JOINT_IDS",
           "MARGIN_DEG", "MOUNT_CLEARANCE_M", "OBJECT_NAMES", "TRAIN", "TRAINABLE"]

#: ``training.TrainConfig()`` (the paper's hyperparameters).
TRAIN = {"n_models": 10, "seed": 0, "torque_epochs": 300, "torque_batch": 256,
         "torque_lr": 3e-4, "attention_epochs": 30, "attention_batch": 32,
         "attention_lr": 1e-4, "set_size": 64, "attention_sets": 1000,
         "attention_val_sets": 200, "w_mass": 1.0, "w_com": 0.3, "val_fraction": 0.1,
         "trainable": "all", "torque_model": "paper", "session_strength": 1.0,
         "current_input": False, "session_terms": False, "attention_torque_spread": 0.0}

#: ``training_setup.TRAINABLE`` (``train --trainable``).
TRAINABLE = ("all", "head", "servo", "servo+input", "servo+attention", "attention")

#: ``training.FINETUNE_DEFAULTS`` (``train --init``).
FINETUNE = {"torque_epochs": 200, "torque_batch": 64, "torque_lr": 1e-4,
            "attention_epochs": 20, "attention_lr": 1e-4, "attention_sets": 250,
            "attention_val_sets": 100}

#: ``design.DEFAULT_MARGIN_DEG``.
MARGIN_DEG = 10.0

#: ``open_manipulator_x.MOUNT_CLEARANCE_M``, ``JOINT_IDS``, ``GRIPPER_ID``.
MOUNT_CLEARANCE_M = 0.10
JOINT_IDS = (11, 12, 13, 14)
GRIPPER_ID = 15

#: ``hardware.driver.ArmConfig.retries``.
BUS_RETRIES = 10

#: ``objects.known_names()``.
OBJECT_NAMES = ("cube", "red", "white", "black", "empty", "50g", "100g", "150g", "<N>g")

#: ``arms.ARMS`` and ``arms.DEFAULT_ARM``.
ARM_NAMES = ("open_manipulator_x", "so101", "koch_v1_1")
DEFAULT_ARM = "open_manipulator_x"
