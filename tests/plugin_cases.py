"""One small, valid configuration of every texture plugin, as a dict and as XML.

Used to test that each plugin loads from ``mi.load_dict``, ``mi.load_string`` and ``mi.load_file``
and that the three give the same texture.
"""

import os

import mitsuba as mi

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.join(HERE, 'data')

CASES = {
    'pbrt_constant': (
        {'value': {'type': 'rgb', 'value': [0.2, 0.4, 0.6]}},
        '<rgb name="value" value="0.2, 0.4, 0.6"/>'),
    'pbrt_scale': (
        {'tex': {'type': 'checkerboard'}, 'scale': 2.0},
        '<texture name="tex" type="checkerboard"/><float name="scale" value="2"/>'),
    'pbrt_mix': (
        {'tex1': {'type': 'rgb', 'value': [1, 0, 0]}, 'tex2': 0.5, 'amount': {'type': 'pbrt_uv'}},
        '<rgb name="tex1" value="1, 0, 0"/><float name="tex2" value="0.5"/>'
        '<texture name="amount" type="pbrt_uv"/>'),
    'pbrt_directionmix': (
        {'tex1': 0.1, 'tex2': 0.9, 'dir': [0, 0, 1]},
        '<float name="tex1" value="0.1"/><float name="tex2" value="0.9"/>'
        '<vector name="dir" x="0" y="0" z="1"/>'),
    'pbrt_bilerp': (
        {'v00': 0.0, 'v01': 1.0, 'v10': 0.5, 'v11': 0.25, 'uscale': 2.0},
        '<float name="v00" value="0"/><float name="v01" value="1"/><float name="v10" value="0.5"/>'
        '<float name="v11" value="0.25"/><float name="uscale" value="2"/>'),
    'pbrt_uv': (
        {'mapping': 'uv', 'uscale': 3.0, 'vdelta': 0.25},
        '<string name="mapping" value="uv"/><float name="uscale" value="3"/>'
        '<float name="vdelta" value="0.25"/>'),
    'pbrt_imagemap': (
        {'filename': os.path.join(DATA, 'rgb_13x17.exr'), 'filter': 'ewa', 'uscale': 2.0},
        f'<string name="filename" value="{os.path.join(DATA, "rgb_13x17.exr")}"/>'
        '<string name="filter" value="ewa"/><float name="uscale" value="2"/>'),
    'pbrt_checkerboard': (
        {'tex1': {'type': 'rgb', 'value': [0.9, 0.9, 0.9]}, 'tex2': 0.1, 'aamode': 'box',
         'uscale': 4.0, 'vscale': 4.0},
        '<rgb name="tex1" value="0.9, 0.9, 0.9"/><float name="tex2" value="0.1"/>'
        '<string name="aamode" value="box"/><float name="uscale" value="4"/>'
        '<float name="vscale" value="4"/>'),
    'pbrt_dots': (
        {'inside': {'type': 'rgb', 'value': [0.8, 0.1, 0.1]}, 'outside': 0.9, 'uscale': 8.0},
        '<rgb name="inside" value="0.8, 0.1, 0.1"/><float name="outside" value="0.9"/>'
        '<float name="uscale" value="8"/>'),
    'pbrt_fbm': (
        {'octaves': 6, 'roughness': 0.6, 'to_world': mi.ScalarTransform4f().scale(0.25)},
        '<integer name="octaves" value="6"/><float name="roughness" value="0.6"/>'
        '<transform name="to_world"><scale value="0.25"/></transform>'),
    'pbrt_wrinkled': (
        {'octaves': 4, 'aamode': 'none'},
        '<integer name="octaves" value="4"/><string name="aamode" value="none"/>'),
    'pbrt_windy': ({}, ''),
    'pbrt_marble': (
        {'scale': 2.0, 'variation': 0.5},
        '<float name="scale" value="2"/><float name="variation" value="0.5"/>'),
    'pbrt_supersample': (
        {'texture': {'type': 'pbrt_checkerboard', 'aamode': 'none', 'uscale': 4.0}, 'samples': 9},
        '<texture name="texture" type="pbrt_checkerboard"><string name="aamode" value="none"/>'
        '<float name="uscale" value="4"/></texture><integer name="samples" value="9"/>'),
}
