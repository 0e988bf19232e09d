import numpy as np
import pytest
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg

from imunoise.daq import ros2_msgs as m

REFERENCE_IMU_TEXT = """std_msgs/Header header
geometry_msgs/Quaternion orientation
float64[9] orientation_covariance
geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance
geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance
================================================================================
MSG: geometry_msgs/Quaternion
float64 x 0
float64 y 0
float64 z 0
float64 w 1
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""


def test_imu_schema_text_is_rosbag2_layout():
    assert m.SCHEMA_TEXT[m.IMU] == REFERENCE_IMU_TEXT


@pytest.mark.parametrize("msgtype", [m.IMU, m.TEMPERATURE, m.DIAGNOSTIC_ARRAY])
def test_type_hash_of_schema_text_equals_ros2_published(msgtype):
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(m.SCHEMA_TEXT[msgtype], msgtype))
    assert store.hash_rihs01(msgtype) == m.TYPE_HASH[msgtype]
    # and the built-in ROS 2 Jazzy definitions agree
    assert get_typestore(Stores.ROS2_JAZZY).hash_rihs01(msgtype) == m.TYPE_HASH[msgtype]


def _reference_imu(msg_t, gyro, accel, frame):
    enc = serialize_dynamic(m.IMU, m.SCHEMA_TEXT[m.IMU])[m.IMU]
    sec, nsec = m.stamps_from_seconds(np.array([msg_t]))
    return enc({
        "header": {"stamp": {"sec": int(sec[0]), "nanosec": int(nsec[0])}, "frame_id": frame},
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        "orientation_covariance": [-1.0] + [0.0] * 8,
        "angular_velocity": dict(zip("xyz", gyro, strict=True)),
        "angular_velocity_covariance": [0.0] * 9,
        "linear_acceleration": dict(zip("xyz", accel, strict=True)),
        "linear_acceleration_covariance": [0.0] * 9})


@pytest.mark.parametrize("frame", ["", "a", "abc", "imu", "imu_link", "adis16350_link",
                                   "x" * 19, "y" * 27])
def test_imu_encoding_is_byte_identical_to_mcap_ros2(frame):
    t = np.array([1.7e9 + 0.123456789, 12.5])
    g = np.array([[1e-3, -2e-3, 3.5], [0.0, 1.0, -1.0]])
    a = np.array([[0.1, 9.81, -0.2], [1.0, 2.0, 3.0]])
    rec = m.encode_imu(t, g, a, frame)
    assert rec.itemsize == 300 + ((12 + len(frame) + 1 + 7) // 8) * 8
    for i in range(2):
        assert rec[i].tobytes() == bytes(_reference_imu(t[i], g[i], a[i], frame))


def test_missing_half_marked_with_minus_one_and_decodes():
    rec = m.encode_imu(np.array([5.0]), np.ones((1, 3)), None, "imu_link")
    dec = generate_dynamic(m.IMU, m.SCHEMA_TEXT[m.IMU])[m.IMU](rec[0].tobytes())
    assert dec.linear_acceleration_covariance[0] == -1.0
    assert dec.angular_velocity_covariance[0] == 0.0
    assert dec.orientation_covariance[0] == -1.0
    assert dec.angular_velocity.y == 1.0 and dec.header.stamp.sec == 5


def test_temperature_and_diagnostics_decode_with_independent_decoder():
    rec = m.encode_temperature(np.array([3.25]), np.array([31.5]), frame_id="imu_link")
    assert rec.itemsize == 44
    dec = generate_dynamic(m.TEMPERATURE, m.SCHEMA_TEXT[m.TEMPERATURE])[m.TEMPERATURE](
        rec[0].tobytes())
    assert dec.temperature == 31.5 and dec.header.stamp.nanosec == 250_000_000
    payload = m.encode_diagnostic_array(7.5, [(m.WARN, "dev/acq", "gap: 3 samples", "dev",
                                               [("event", "gap"), ("missing", "3")])])
    dec = generate_dynamic(m.DIAGNOSTIC_ARRAY, m.SCHEMA_TEXT[m.DIAGNOSTIC_ARRAY])[
        m.DIAGNOSTIC_ARRAY](payload)
    st = dec.status[0]
    assert (st.level, st.name, st.message, st.hardware_id) == (1, "dev/acq", "gap: 3 samples",
                                                               "dev")
    assert [(kv.key, kv.value) for kv in st.values] == [("event", "gap"), ("missing", "3")]


def test_stamps_split_exactly():
    sec, nsec = m.stamps_from_seconds(np.array([0.0, 1.999999999, 1.7e9 + 0.5]))
    assert sec.tolist() == [0, 1, 1_700_000_000]
    assert nsec.tolist() == [0, 999_999_999, 500_000_000]
