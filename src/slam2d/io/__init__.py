"""Readers and writers: g2o, TORO and iSAM pose/landmark graph text formats."""

from slam2d.io._text import GraphFile as GraphFile
from slam2d.io._text import GraphFormatError as GraphFormatError
from slam2d.io._text import GraphFormatWarning as GraphFormatWarning
from slam2d.io.g2o import read_g2o as read_g2o
from slam2d.io.g2o import write_g2o as write_g2o
