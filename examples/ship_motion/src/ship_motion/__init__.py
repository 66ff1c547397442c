"""RAP's second case study: predicting a ship's motion, and retraining the predictor online.

- :mod:`ship_motion.physics`: the ship (a 3-DOF manoeuvring model), its weather, its route.
- :mod:`ship_motion.predict`: kinematic, dynamic and data-driven predictors, and their score.
- :mod:`ship_motion.learn`: training the data-driven model, ONNX export, judging candidates.
"""
