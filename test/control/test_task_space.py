"""Task coordinates read from the model's markers: the positions' components, and a Jacobian that
is their derivative (central differences)."""
import numpy as np

from soft_arm_control.task_space import TaskSpace
from soft_arm_model import marker_positions, solve_equilibrium


def test_the_task_coordinates_and_their_jacobian(paper_model, rng):
    task = TaskSpace((3, 3, 3, 2, 0), (0, 1, 2, 1, 2))
    q = solve_equilibrium(paper_model, np.array([1.2, 0.4, 0.9, 0.3])).q
    q = q + 0.02 * rng.standard_normal(paper_model.n)
    x, J = task.evaluate(paper_model, q)
    markers = marker_positions(paper_model, q)
    assert np.array_equal(x, markers[[3, 3, 3, 2, 0], [0, 1, 2, 1, 2]])
    h = 1e-6
    fd = np.empty_like(J)
    for j in range(paper_model.n):
        e = np.zeros(paper_model.n)
        e[j] = h
        fd[:, j] = (task.evaluate(paper_model, q + e)[0] - task.evaluate(paper_model, q - e)[0]) / (2 * h)
    assert np.abs(J - fd).max() <= 1e-6 * np.abs(fd).max()
