"""Kinematics: parameter specs, the five skid-steer models and the extensions that augment them."""

# The modules of this package (the API is theirs; ``skidkin_ros`` re-exports the public part).
__all__ = [
    'augmented',
    'extensions',
    'models',
    'sparse_library',
    'specs',
]
