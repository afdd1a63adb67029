"""Kinematics: parameter specs, the five skid-steer models and the extensions that augment them."""
