import numpy as np

from deepword.colour import hue_rotation


def test_hue_rotation_turns_colours_about_the_grey_axis():
    red, grey = np.array([200.0, 30.0, 30.0]), np.array([90.0, 90.0, 90.0])
    half = hue_rotation(0.5)
    assert np.allclose(half @ grey, grey) and np.allclose(hue_rotation(1.0), np.eye(3))
    assert np.allclose(half @ half, np.eye(3)) and np.allclose(hue_rotation(0.2) @ hue_rotation(-0.2), np.eye(3))
    luma = np.array([0.299, 0.587, 0.114])
    turned = half @ red
    assert np.isclose(luma @ turned, luma @ red)          # the brightness stays
    assert turned[0] < turned[1] and turned[0] < turned[2]  # red turns towards cyan


def test_hue_rotation_of_many_turns_is_one_matrix_per_turn():
    turns = np.array([[0.1, -0.3], [0.5, 0.0]])
    many = hue_rotation(turns)
    assert many.shape == (2, 2, 3, 3)
    for i in range(2):
        for j in range(2):
            assert np.allclose(many[i, j], hue_rotation(float(turns[i, j])))
