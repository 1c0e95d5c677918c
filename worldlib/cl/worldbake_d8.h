/* D8 neighbour offsets, codes 0..7 = N, NE, E, SE, S, SW, W, NW (pysheds'
 * order); row 0 is north. The numpy twin is DR, DC in
 * worldlib/flow/reference.py. Included with #include "worldbake_d8.h". */
#ifndef WORLDBAKE_D8_H
#define WORLDBAKE_D8_H

__constant int DR[8] = {-1, -1, 0, 1, 1, 1, 0, -1};
__constant int DC[8] = {0, 1, 1, 1, 0, -1, -1, -1};

#endif
