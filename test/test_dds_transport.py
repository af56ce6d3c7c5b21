"""The graph's Fast DDS profile: set for the graph's processes unless the user chose one."""
import xml.etree.ElementTree as ET

from multicam_ego_motion.ros_plumbing import dds_transport

NS = '{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}'


def test_profile_is_set_unless_the_user_chose_one_or_another_rmw():
    env = {}
    assert dds_transport.use_graph_profile(env)
    assert env == {'FASTRTPS_DEFAULT_PROFILES_FILE': str(dds_transport.profile())}
    mine = {'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/my_profile.xml'}
    assert not dds_transport.use_graph_profile(mine)
    assert mine == {'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/my_profile.xml'}
    cyclone = {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}
    assert not dds_transport.use_graph_profile(cyclone)
    assert 'FASTRTPS_DEFAULT_PROFILES_FILE' not in cyclone


def test_profile_gives_a_shared_memory_segment_for_two_vga_frames():
    root = ET.parse(dds_transport.profile()).getroot()
    shm = [d for d in root.iter(NS + 'transport_descriptor') if d.find(NS + 'type').text == 'SHM']
    assert len(shm) == 1
    # two frames in flight of four 640x480 mono images, with room for the rest of the traffic
    assert int(shm[0].find(NS + 'segment_size').text) >= 2 * 4 * 640 * 480 * 1.5
    participant = root.find(NS + 'participant')
    assert participant.get('is_default_profile') == 'true'
    used = [t.text for t in participant.iter(NS + 'transport_id')]
    assert shm[0].find(NS + 'transport_id').text in used
