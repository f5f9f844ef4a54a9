"""Reading and writing files: g2o, TORO and iSAM graph formats, TUM trajectory export, dataset loaders."""

from slam2d.io._text import GraphFile as GraphFile
from slam2d.io._text import GraphFormatError as GraphFormatError
from slam2d.io._text import GraphFormatWarning as GraphFormatWarning
from slam2d.io.g2o import read_g2o as read_g2o
from slam2d.io.g2o import write_g2o as write_g2o
from slam2d.io.graph_files import FORMATS as FORMATS
from slam2d.io.graph_files import detect_format as detect_format
from slam2d.io.graph_files import read_graph as read_graph
from slam2d.io.isam import read_isam as read_isam
from slam2d.io.isam import write_isam as write_isam
from slam2d.io.toro import read_toro as read_toro
from slam2d.io.toro import write_toro as write_toro
