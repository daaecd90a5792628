import numpy as np

from stages.rays import box_interval

BOX = np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 2.0]])


def test_rays_enter_and_leave_the_box_where_its_faces_are():
    origins = np.array([[-3.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 5.0]])
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    enter, leave = box_interval(origins, directions, BOX)
    np.testing.assert_allclose(enter, [2.0, 0.0, 3.0])  # a ray from inside enters at its origin
    np.testing.assert_allclose(leave, [4.0, 1.0, 5.0])


def test_a_ray_that_misses_or_points_away_gets_an_empty_interval():
    origins = np.array([[-3.0, 5.0, 1.0], [-3.0, 0.0, 1.0]])
    directions = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    enter, leave = box_interval(origins, directions, BOX)
    assert np.all(enter > leave)


def test_an_axis_parallel_ray_on_a_face_is_not_cut_by_that_face_and_one_origin_serves_many_rays():
    enter, leave = box_interval(np.array([-3.0, 1.0, 1.0]), np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.1]]), BOX)
    np.testing.assert_allclose(enter, [2.0, 2.0])
    np.testing.assert_allclose(leave, [4.0, 4.0])
