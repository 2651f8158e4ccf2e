"""param_table.IMU_CALIBRATION_PARAMS (the shared IMU calibration as a parameter table) and
imu_calibration (the core ImuCalibration of its declared values)."""
import numpy as np
import pytest

from ar_tracking.ros.param_table import IMU_CALIBRATION_PARAMS, imu_calibration


def test_the_table_keeps_the_declaration_order_and_checks() -> None:
    assert [s.name for s in IMU_CALIBRATION_PARAMS] == ['hard_iron_offset', 'gyro_bias', 'accel_bias', 'soft_iron_matrix']
    by_name = {s.name: s for s in IMU_CALIBRATION_PARAMS}
    assert by_name['gyro_bias'].validator()([0.0, 0.0]) == 'needs 3 values, got 2'
    assert by_name['soft_iron_matrix'].validator()([0.0] * 9) == 'matrix is singular'
    assert by_name['soft_iron_matrix'].validator()(by_name['soft_iron_matrix'].default) is None


def test_imu_calibration_adds_the_extra_hard_iron() -> None:
    values = {'hard_iron_offset': [1e-6, 2e-6, 3e-6], 'gyro_bias': [0.01, 0.0, 0.0], 'accel_bias': [0.0, 0.1, 0.0],
              'soft_iron_matrix': [2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]}
    c = imu_calibration(values, extra_hard_iron=[0.0, 5e-7, 0.0])
    assert np.allclose(c.hard_iron_offset, [1e-6, 2.5e-6, 3e-6], rtol=0, atol=1e-15)
    assert np.allclose(c.gyro_bias, [0.01, 0.0, 0.0]) and np.allclose(c.accel_bias, [0.0, 0.1, 0.0])
    assert np.allclose(np.reshape(c.soft_iron_matrix, (3, 3)), np.diag([2.0, 1.0, 1.0]))
    with pytest.raises(KeyError):
        imu_calibration({k: v for k, v in values.items() if k != 'gyro_bias'})
